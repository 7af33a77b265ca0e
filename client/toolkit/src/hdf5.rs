//! D4RL HDF5 files and Minari datasets into [`Trajectories`] (feature `hdf5`).
//!
//! The decoder is `hdf5-reader`, pure Rust (no libhdf5 on any machine; gzip/deflate and
//! shuffle filters included), read-only.
//!
//! Module map:
//! - [`read_hdf5`]: any supported file or directory; tells the two layouts apart.
//! - [`read_d4rl`]: D4RL's layout: top-level datasets `observations` `[N, obs_dim]`, `actions`
//!   `[N, act_dim]` (N > 0), optional `terminals`, `timeouts` (`[N]`, bool or numbers 0/1),
//!   `episode_starts` / `episode_lengths` and maze walls (`walls` / `wall_map` / `maze_map`),
//!   by the rules of [`crate::episodes`]. `rewards`, `infos/...` and everything else are left
//!   out (listed in [`Trajectories::ignored`]).
//! - [`read_minari`]: Minari's on-disk layout: `main_data.hdf5` (or a Minari dataset directory
//!   holding `data/main_data.hdf5`) with one group `episode_<id>` per episode, in id order.
//!   Each holds `observations` (`[T + 1, ...]`: the state after every action, plus the first),
//!   `actions` `[T, ...]`, `terminations` and `truncations` `[T]`. The last observation of an
//!   episode has no action and is dropped, so row k pairs a state with the action taken in it
//!   (D4RL's layout); each episode's first row is flagged in `episode_starts`. An episode of
//!   zero steps (observations `[1, ...]`, actions `[0, ...]`) has no row: it is skipped, named
//!   in [`Trajectories::notes`].
//!
//! **Dict observations** (a group instead of a dataset, e.g. PointMaze's `achieved_goal`,
//! `desired_goal`, `observation`) are flattened the way gymnasium's `spaces.flatten` does for
//! a `Dict` space built from a plain dict: keys in sorted order, nested groups recursively,
//! each entry's trailing dimensions row-major, concatenated per row. PointMaze rows are
//! therefore `[achieved_goal (2), desired_goal (2), observation (4)]`. A **Tuple** space's
//! parts, stored as `_index_0`, `_index_1`, ..., go by their number (`_index_10` after
//! `_index_9`), before any other key. A `Discrete` part is read as its integer (gymnasium's
//! `flatten` would one-hot it; the file does not say how many values it takes). Dict actions
//! are refused (no environment we know of has them). **JPEG frames**: when the dataset's
//! `metadata.json` says `jpeg_encoding = true` (minari 0.5's `DataCollector` default for uint8
//! images of at least 32 x 32), observations stored as variable-length uint8 sequences, or as
//! uint8 data that begins with JPEG's signature, are refused naming the setting; others are read
//! as usual.
//!
//! Values follow the rules of [`crate::values`], as the `.npz` reader does: any integer or float
//! type (float16 included) in either byte order, read as float32 (float64 data is rounded, as
//! the server's training does) and refused where not finite as float32, naming the key, row and
//! coordinate (only in the rows kept: Minari's dropped last observation is not checked); `[N]`
//! is `[N, 1]` and more dimensions are flattened row-major; flags are h5py's bool (an enum over
//! int8) or numbers that are all 0 or 1. Any other HDF5 type is refused, described in words.

use std::path::{Path, PathBuf};

use hdf5_reader::group::Group;
use hdf5_reader::{ByteOrder, Dataset, Datatype, Hdf5File};

use crate::episodes;
use crate::trajectories::Trajectories;
use crate::values::{self, Element, Kind};

/// Why a file cannot be read: the file and what is wrong, naming the key or group.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct Hdf5Error {
    pub path: PathBuf,
    pub message: String,
}

pub type Result<T, E = Hdf5Error> = std::result::Result<T, E>;

/// Whether a path is for this module's readers: a file with HDF5's signature, or a directory
/// (the only directory form a dataset takes is Minari's, so [`read_hdf5`] says what is wrong
/// with one that is not a Minari dataset, rather than another reader failing to open it).
pub fn is_hdf5(path: &Path) -> bool {
    if path.is_dir() {
        return true;
    }
    if std::fs::metadata(path).is_err() && path.symlink_metadata().is_ok() {
        return true; // a link that cannot be followed: read_hdf5 names it
    }
    let mut magic = [0u8; 8];
    std::fs::File::open(path).and_then(|mut f| std::io::Read::read_exact(&mut f, &mut magic)).is_ok()
        && magic == *b"\x89HDF\r\n\x1a\n"
}

/// `dir/data/main_data.hdf5` or `dir/main_data.hdf5`, the first that exists; one that exists
/// but is no readable file (a directory, a dangling link, a symlink loop) is named as such.
fn minari_file(dir: &Path) -> Result<PathBuf> {
    for p in [dir.join("data").join("main_data.hdf5"), dir.join("main_data.hdf5")] {
        match std::fs::metadata(&p) {
            Ok(m) if m.is_file() => return Ok(p),
            Ok(_) => return Err(err(&p, "is a directory, not Minari's main_data.hdf5 file")),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && p.symlink_metadata().is_err() => {}
            Err(e) => return Err(unreadable(&p, &e)),
        }
    }
    Err(err(dir, "a directory without data/main_data.hdf5 (not a Minari dataset)"))
}

/// A D4RL file or a Minari dataset: Minari when the root holds `episode_*` groups and no
/// `observations`, D4RL otherwise.
pub fn read_hdf5(path: &Path) -> Result<Trajectories> {
    let file_path = data_file(path)?;
    let (root, groups, datasets) = read_root(&file_path)?;
    if !datasets.iter().any(|d| d == "observations") && groups.iter().any(|g| g.starts_with("episode_")) {
        minari_from(&file_path, &root, &groups, &datasets)
    } else {
        d4rl_from(&file_path, &root, &groups, &datasets)
    }
}

/// A D4RL-layout file (module docs).
pub fn read_d4rl(path: &Path) -> Result<Trajectories> {
    let (root, groups, datasets) = read_root(path)?;
    d4rl_from(path, &root, &groups, &datasets)
}

/// A Minari dataset: its `main_data.hdf5` or its directory (module docs).
pub fn read_minari(path: &Path) -> Result<Trajectories> {
    let file_path = data_file(path)?;
    let (root, groups, datasets) = read_root(&file_path)?;
    minari_from(&file_path, &root, &groups, &datasets)
}

/// The HDF5 file a path names: the path itself, or a Minari directory's `main_data.hdf5`.
fn data_file(path: &Path) -> Result<PathBuf> {
    if path.is_dir() {
        minari_file(path)
    } else if let Err(e) = std::fs::metadata(path) {
        Err(unreadable(path, &e))
    } else {
        Ok(path.to_owned())
    }
}

/// Opens a file and lists its root: the root group, its member groups and its datasets.
fn read_root(path: &Path) -> Result<(Group, Vec<String>, Vec<String>)> {
    let file = open(path)?;
    let root = file.root_group().map_err(|e| err(path, format!("reading the root group: {e}")))?;
    let (groups, datasets) = root.member_names().map_err(|e| err(path, format!("listing the root: {e}")))?;
    Ok((root, groups, datasets))
}

/// A path that exists (at least as a link) but cannot be opened: the OS's reason, and the two
/// usual causes, which its message does not name.
fn unreadable(path: &Path, e: &std::io::Error) -> Hdf5Error {
    let link = path.symlink_metadata().is_ok_and(|m| m.file_type().is_symlink());
    let cause = if link { " (a dangling link or a symlink loop)" } else { "" };
    err(path, format!("cannot be opened: {e}{cause}"))
}

fn err(path: &Path, message: impl Into<String>) -> Hdf5Error {
    Hdf5Error { path: path.to_owned(), message: message.into() }
}

fn open(path: &Path) -> Result<Hdf5File> {
    Hdf5File::open(path).map_err(|e| err(path, format!("not a readable HDF5 file: {e}")))
}

/// What kind of numbers a dataset holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Class {
    Bool,
    Integer,
    Float,
}

/// An HDF5 type the readers do not decode, in words (`a 16-byte float`, `a string`).
fn describe(dtype: &Datatype) -> String {
    match dtype {
        Datatype::FixedPoint { size, signed, .. } => {
            format!("a {size}-byte {} integer", if *signed { "signed" } else { "unsigned" })
        }
        Datatype::FloatingPoint { size, .. } => format!("a {size}-byte float"),
        Datatype::String { .. } => "a string".to_owned(),
        Datatype::VarLen { kind: hdf5_reader::VarLenKind::String, .. } => "a variable-length string".to_owned(),
        Datatype::VarLen { .. } => "a variable-length sequence".to_owned(),
        Datatype::Compound { fields, .. } => {
            format!("a compound type of {} fields (a record, or complex numbers)", fields.len())
        }
        Datatype::Array { dims, .. } => format!("an array type of shape {dims:?} per element"),
        Datatype::Enum { base, .. } => format!("an enum over {}", describe(base)),
        Datatype::Opaque { size, .. } => format!("{size} opaque bytes"),
        Datatype::Reference { .. } => "a reference".to_owned(),
        Datatype::Bitfield { size, .. } => format!("a {size}-byte bitfield"),
    }
}

/// The element type of a dataset, or what it is in words. h5py writes numpy bool as an enum
/// FALSE = 0, TRUE = 1 over int8, read as bool.
fn element_of(dtype: &Datatype, key: &str) -> std::result::Result<(Element, Class), String> {
    let unsupported = || format!("'{key}' holds {}; expected integers, floats or bool", describe(dtype));
    let (base, class) = match dtype {
        Datatype::Enum { base, .. } => (base.as_ref(), Class::Bool),
        other => (other, Class::Integer),
    };
    let (kind, size, order) = match base {
        Datatype::FixedPoint { size, signed, byte_order } => {
            (if *signed { Kind::Int } else { Kind::Uint }, *size, *byte_order)
        }
        Datatype::FloatingPoint { size, byte_order } if class != Class::Bool => (Kind::Float, *size, *byte_order),
        _ => return Err(unsupported()),
    };
    let element = Element::new(kind, usize::from(size), order == ByteOrder::BigEndian).ok_or_else(unsupported)?;
    let class = match (class, kind) {
        (Class::Bool, _) => Class::Bool,
        (_, Kind::Float) => Class::Float,
        _ => Class::Integer,
    };
    Ok((element, class))
}

/// A numeric dataset as f64 with its shape and class. Errors name `key`.
fn numbers(ds: &Dataset, key: &str) -> std::result::Result<(Vec<u64>, Vec<f64>, Class), String> {
    let shape = ds.shape().to_vec();
    let (element, class) = element_of(ds.dtype(), key)?;
    let raw = ds.read_raw_bytes().map_err(|e| format!("'{key}': {e}"))?;
    Ok((shape, element.decode_all(&raw), class))
}

/// `[N, width]` float32 values of a dataset by the row rule of [`crate::values`] (`[N]` is
/// `[N, 1]`, more dimensions are flattened row-major), and its stored shape. Values must be
/// finite as float32 in the first `keep` rows (every row when `None`).
fn rows_of(ds: &Dataset, key: &str, keep: Option<usize>) -> std::result::Result<(usize, usize, Vec<f32>), String> {
    let (shape, values, class) = numbers(ds, key)?;
    let shown = format!("'{key}'");
    if class == Class::Bool {
        return Err(format!("{shown} is bool; expected integers or floats (read as float32)"));
    }
    let (n, width) = values::row_shape(&shown, &shape)?;
    let values = values::rows_to_f32(&shown, &values, &shape, keep)?;
    Ok((n, width, values))
}

/// `[N]` flags of a dataset: bool, or integers or floats that are all 0 or 1.
fn flags_of(ds: &Dataset, key: &str, rows: usize) -> std::result::Result<Vec<bool>, String> {
    let (shape, values, _) = numbers(ds, key)?;
    if shape.len() != 1 || shape[0] as usize != rows {
        return Err(format!("'{key}' has shape {shape:?}; episode flags must be [N] with N = {rows}"));
    }
    values::flags(&format!("'{key}'"), &values)
}

fn d4rl_from(path: &Path, root: &Group, groups: &[String], datasets: &[String]) -> Result<Trajectories> {
    let e = |m: String| err(path, m);
    let get = |key: &str| -> Result<Option<Dataset>> {
        if !datasets.iter().any(|d| d == key) {
            return Ok(None);
        }
        root.dataset(key).map(Some).map_err(|x| err(path, format!("'{key}': {x}")))
    };
    let required = |key: &str| -> Result<Dataset> {
        get(key)?.ok_or_else(|| {
            err(path, format!("no '{key}' dataset at the top level (it holds {})", list(datasets, groups)))
        })
    };
    let (n, obs_dim, observations) = rows_of(&required("observations")?, "observations", None).map_err(e)?;
    if n == 0 {
        return Err(err(path, "'observations' has no rows (N = 0); a dataset needs at least one"));
    }
    let (na, act_dim, actions) = rows_of(&required("actions")?, "actions", None).map_err(e)?;
    if na != n {
        return Err(err(path, format!("'actions' has {na} rows but 'observations' has {n}")));
    }
    let mut t = Trajectories { observations, obs_dim, actions, act_dim, ..Default::default() };
    for (name, alias) in [("terminals", "terminations"), ("timeouts", "truncations")] {
        let (a, b) = (get(name)?, get(alias)?);
        if a.is_some() && b.is_some() {
            return Err(err(path, format!("holds both '{name}' and its Minari alias '{alias}'; keep only one")));
        }
        if let Some((key, ds)) = a.map(|d| (name, d)).or(b.map(|d| (alias, d))) {
            let flags = flags_of(&ds, key, n).map_err(e)?;
            if name == "terminals" { t.terminals = flags } else { t.timeouts = flags }
        }
    }
    let starts = get("episode_starts")?.map(|d| numbers(&d, "episode_starts")).transpose().map_err(e)?;
    let lengths = get("episode_lengths")?.map(|d| numbers(&d, "episode_lengths")).transpose().map_err(e)?;
    if let Some((flags, _)) = episodes::explicit_starts(
        n,
        starts.as_ref().map(|(s, v, c)| (s.as_slice(), v.as_slice(), *c == Class::Bool, *c != Class::Float)),
        lengths.as_ref().map(|(s, v, c)| (s.as_slice(), v.as_slice(), *c != Class::Float)),
    )
    .map_err(e)?
    {
        t.episode_starts = flags;
    }
    let mut found = Vec::new();
    for key in episodes::WALL_KEYS {
        if let Some(ds) = get(key)? {
            let (shape, values, _) = numbers(&ds, key).map_err(e)?;
            found.push((key, shape, values));
        }
    }
    t.walls = episodes::pick_walls(&found).map_err(e)?;
    let used = [
        "observations",
        "actions",
        "terminals",
        "terminations",
        "timeouts",
        "truncations",
        "episode_starts",
        "episode_lengths",
        "walls",
        "wall_map",
        "maze_map",
    ];
    t.ignored = datasets
        .iter()
        .filter(|d| !used.contains(&d.as_str()))
        .cloned()
        .chain(groups.iter().map(|g| format!("{g}/")))
        .collect();
    Ok(t)
}

fn list(datasets: &[String], groups: &[String]) -> String {
    let all: Vec<String> =
        datasets.iter().map(|d| format!("'{d}'")).chain(groups.iter().map(|g| format!("group '{g}'"))).collect();
    if all.is_empty() { "nothing".to_owned() } else { all.join(", ") }
}

/// A dataset or a (dict) group, flattened per row by the module's rule: `(rows, width,
/// values)`, finite as float32 in the first `keep` rows (all when `None`); with `jpeg` (Minari's
/// metadata says `jpeg_encoding`), a dataset of JPEG frames is refused ([`jpeg_frames`]). `at`
/// names the place in errors.
fn flattened(
    group: &Group,
    name: &str,
    at: &str,
    keep: Option<usize>,
    jpeg: bool,
) -> std::result::Result<(usize, usize, Vec<f32>), String> {
    let (groups, datasets) = group.member_names().map_err(|e| format!("{at}: {e}"))?;
    if datasets.iter().any(|d| d == name) {
        let ds = group.dataset(name).map_err(|e| format!("{at}/{name}: {e}"))?;
        let refused = || format!("'{at}/{name}' is {JPEG_ENCODED}");
        if jpeg && jpeg_frames(ds.dtype(), None) {
            return Err(refused());
        }
        let rows = rows_of(&ds, &format!("{at}/{name}"), keep)?;
        if jpeg && jpeg_frames(ds.dtype(), Some(&rows.2)) {
            return Err(refused());
        }
        return Ok(rows);
    }
    if !groups.iter().any(|g| g == name) {
        return Err(format!("no '{name}' in {at}"));
    }
    let sub = group.group(name).map_err(|e| format!("{at}/{name}: {e}"))?;
    let (mut keys_g, keys_d) = sub.member_names().map_err(|e| format!("{at}/{name}: {e}"))?;
    keys_g.extend(keys_d);
    keys_g.sort_by(|a, b| flatten_order(a).cmp(&flatten_order(b)));
    if keys_g.is_empty() {
        return Err(format!("{at}/{name} is an empty group"));
    }
    let here = format!("{at}/{name}");
    let parts: Vec<(usize, usize, Vec<f32>)> =
        keys_g.iter().map(|k| flattened(&sub, k, &here, keep, jpeg)).collect::<std::result::Result<_, _>>()?;
    let rows = parts[0].0;
    if let Some((k, p)) = keys_g.iter().zip(&parts).find(|(_, p)| p.0 != rows) {
        return Err(format!("{here}/{k} has {} rows but {here}/{} has {rows}", p.0, keys_g[0]));
    }
    let width: usize = parts.iter().map(|p| p.1).sum();
    let mut values = Vec::with_capacity(rows * width);
    for r in 0..rows {
        for (_, w, v) in &parts {
            values.extend_from_slice(&v[r * w..(r + 1) * w]);
        }
    }
    Ok((rows, width, values))
}

/// Where a member of a Dict or Tuple group goes in a flattened row: Minari stores a Tuple's
/// parts as `_index_0`, `_index_1`, ..., which go by their number (not as strings: `_index_10`
/// after `_index_9`), before any other key; a Dict's keys go in string order.
fn flatten_order(key: &str) -> (u8, u64, &str) {
    match key
        .strip_prefix("_index_")
        .and_then(|n| n.parse::<u64>().ok().filter(|_| n.bytes().all(|b| b.is_ascii_digit())))
    {
        Some(i) => (0, i, key),
        None => (1, 0, key),
    }
}

/// What the message for JPEG-encoded frames says after its place.
const JPEG_ENCODED: &str = "JPEG-encoded by Minari's DataCollector (data/metadata.json: jpeg_encoding = true); \
    relreward reads raw arrays: record with DataCollector(..., jpeg_encoding=False), or decode the frames into an .npz";

/// Whether the dataset's `metadata.json` (beside `main_data.hdf5`) says Minari JPEG-encoded
/// its image observations (minari 0.5's DataCollector does by default for uint8 images of at
/// least 32 x 32). Absent or unreadable metadata says no: the data itself is read as it is.
fn jpeg_encoded(file_path: &Path) -> bool {
    let Some(text) = file_path.parent().and_then(|d| std::fs::read_to_string(d.join("metadata.json")).ok()) else {
        return false;
    };
    serde_json::from_str::<serde_json::Value>(&text)
        .ok()
        .and_then(|m| m.get("jpeg_encoding").and_then(serde_json::Value::as_bool))
        .unwrap_or(false)
}

/// Whether a dataset read under Minari's `jpeg_encoding` holds JPEG frames: variable-length
/// uint8 sequences (told by the type, before any read), or uint8 data whose first values are
/// JPEG's signature FF D8 FF (told from the values [`flattened`] read anyway).
fn jpeg_frames(dtype: &Datatype, values: Option<&[f32]>) -> bool {
    let byte = |t: &Datatype| matches!(t, Datatype::FixedPoint { size: 1, signed: false, .. });
    match (dtype, values) {
        (Datatype::VarLen { kind, base, .. }, _) => *kind != hdf5_reader::VarLenKind::String && byte(base),
        (t, Some(v)) => byte(t) && v.starts_with(&[255.0, 216.0, 255.0]),
        _ => false,
    }
}

fn minari_from(path: &Path, root: &Group, groups: &[String], datasets: &[String]) -> Result<Trajectories> {
    let e = |m: String| err(path, m);
    let episodes = episode_groups(groups, datasets).map_err(e)?;
    let jpeg = jpeg_encoded(path);
    let mut t = Trajectories::default();
    let mut skipped = Vec::new();
    let mut ignored: Vec<String> = Vec::new();
    for (_, name) in &episodes {
        let ep = root.group(name).map_err(|x| err(path, format!("group '{name}': {x}")))?;
        let (ep_groups, ep_datasets) = ep.member_names().map_err(|x| err(path, format!("group '{name}': {x}")))?;
        // Members the layout does not take (Minari's `rewards`, `infos/`, ...) are named, once each.
        for key in ep_datasets.iter().cloned().chain(ep_groups.iter().map(|g| format!("{g}/"))) {
            let taken =
                matches!(key.as_str(), "observations" | "observations/" | "actions" | "terminations" | "truncations");
            if !taken && !ignored.contains(&key) {
                ignored.push(key);
            }
        }
        if !ep_datasets.iter().any(|d| d == "actions") {
            return Err(err(path, format!("'{name}/actions' is missing or a group (dict actions are not supported)")));
        }
        let (steps, act_dim, actions) = flattened(&ep, "actions", name, None, false).map_err(e)?;
        if steps == 0 {
            // No action, so no row: nothing to read (its observations are its first state only).
            skipped.push(format!("'{name}'"));
            continue;
        }
        // The last observation is dropped: only the rows kept must be finite.
        let (n_obs, obs_dim, observations) = flattened(&ep, "observations", name, Some(steps), jpeg).map_err(e)?;
        if n_obs != steps + 1 {
            return Err(err(
                path,
                format!("'{name}/observations' has {n_obs} rows for {steps} actions; Minari stores one more"),
            ));
        }
        if t.is_empty() && t.obs_dim == 0 {
            (t.obs_dim, t.act_dim) = (obs_dim, act_dim);
        } else if (t.obs_dim, t.act_dim) != (obs_dim, act_dim) {
            return Err(err(
                path,
                format!(
                    "'{name}' has observations of {obs_dim} and actions of {act_dim} values per row; earlier \
                     episodes have {} and {}",
                    t.obs_dim, t.act_dim
                ),
            ));
        }
        t.observations.extend_from_slice(&observations[..steps * obs_dim]);
        t.actions.extend_from_slice(&actions);
        for (key, out) in [("terminations", &mut t.terminals), ("truncations", &mut t.timeouts)] {
            let flags = if ep_datasets.iter().any(|d| d == key) {
                let ds = ep.dataset(key).map_err(|x| err(path, format!("'{name}/{key}': {x}")))?;
                flags_of(&ds, &format!("{name}/{key}"), steps).map_err(e)?
            } else {
                return Err(err(path, format!("no '{name}/{key}'")));
            };
            out.extend(flags);
        }
        t.episode_starts.push(true);
        t.episode_starts.extend(std::iter::repeat_n(false, steps - 1));
    }
    if t.is_empty() {
        return Err(err(path, "every episode is empty (no actions)"));
    }
    if !skipped.is_empty() {
        t.notes.push(format!("skipped {} empty episode(s) (no steps): {}", skipped.len(), skipped.join(", ")));
    }
    ignored.sort();
    t.ignored = ignored;
    Ok(t)
}

/// The root's episode groups `episode_<id>` in id order. Minari's root holds nothing else, so
/// any other member (a group whose id is not a decimal number, such as `episode_abc`, a second
/// spelling of an id, such as `episode_01` beside `episode_1`, or a dataset) is refused, naming
/// it: leaving it out would upload part of the recording without a word.
fn episode_groups<'a>(
    groups: &'a [String],
    datasets: &[String],
) -> std::result::Result<Vec<(u64, &'a String)>, String> {
    let mut episodes: Vec<(u64, &String)> = Vec::with_capacity(groups.len());
    let mut others = Vec::new();
    for g in groups {
        let id = g.strip_prefix("episode_").filter(|id| !id.is_empty() && id.bytes().all(|b| b.is_ascii_digit()));
        match id.and_then(|id| id.parse::<u64>().ok()) {
            Some(id) => episodes.push((id, g)),
            None => others.push(format!("group '{g}'")),
        }
    }
    others.extend(datasets.iter().map(|d| format!("dataset '{d}'")));
    if episodes.is_empty() {
        return Err("no 'episode_<id>' groups (not a Minari main_data.hdf5)".to_owned());
    }
    if !others.is_empty() {
        return Err(format!(
            "the root holds {} that {} not an episode group 'episode_<id>' (id in decimal digits); a Minari \
             main_data.hdf5 holds only episode groups, so the file is refused rather than uploaded without {}",
            others.join(", "),
            if others.len() == 1 { "is" } else { "are" },
            if others.len() == 1 { "it" } else { "them" },
        ));
    }
    episodes.sort();
    if let Some(pair) = episodes.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(format!("groups '{}' and '{}' are both episode {}", pair[0].1, pair[1].1, pair[0].0));
    }
    Ok(episodes)
}

#[cfg(test)]
mod tests {
    use hdf5_reader::{CompoundField, StringEncoding, StringPadding, StringSize, VarLenKind};

    use super::*;

    #[test]
    fn unsupported_types_are_described_in_words() {
        let le = ByteOrder::LittleEndian;
        let f128 = Datatype::FloatingPoint { size: 16, byte_order: le };
        let string = Datatype::String {
            size: StringSize::Variable,
            encoding: StringEncoding::Utf8,
            padding: StringPadding::NullTerminate,
        };
        let vlen = Datatype::VarLen {
            base: Box::new(Datatype::FixedPoint { size: 1, signed: false, byte_order: le }),
            kind: VarLenKind::String,
            encoding: StringEncoding::Utf8,
            padding: StringPadding::NullTerminate,
        };
        let field = |name: &str, byte_offset| CompoundField {
            name: name.to_owned(),
            byte_offset,
            datatype: Datatype::FloatingPoint { size: 8, byte_order: le },
        };
        let complex = Datatype::Compound { size: 16, fields: vec![field("r", 0), field("i", 8)] };
        let int16bytes = Datatype::FixedPoint { size: 16, signed: true, byte_order: le };
        for (dtype, words) in [
            (f128, "holds a 16-byte float;"),
            (string, "holds a string;"),
            (vlen, "holds a variable-length string;"),
            (complex, "holds a compound type of 2 fields (a record, or complex numbers);"),
            (int16bytes, "holds a 16-byte signed integer;"),
        ] {
            let err = element_of(&dtype, "episode_0/observations").expect_err("unsupported");
            assert!(err.starts_with("'episode_0/observations' ") && err.contains(words), "{err}");
            assert!(!err.contains('{'), "no debug dump: {err}");
        }
        // float16 and every integer size in either byte order are read.
        for size in [2, 4, 8] {
            let (e, class) =
                element_of(&Datatype::FloatingPoint { size, byte_order: ByteOrder::BigEndian }, "x").expect("float");
            assert_eq!((e.kind, e.size, e.big_endian, class), (Kind::Float, usize::from(size), true, Class::Float));
        }
        for size in [1, 2, 4, 8] {
            let (e, class) =
                element_of(&Datatype::FixedPoint { size, signed: false, byte_order: le }, "x").expect("int");
            assert_eq!((e.kind, e.size, class), (Kind::Uint, usize::from(size), Class::Integer));
        }
    }
}
