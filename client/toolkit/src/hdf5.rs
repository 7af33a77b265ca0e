//! D4RL HDF5 files and Minari datasets into [`Trajectories`] (feature `hdf5`).
//!
//! The decoder is `hdf5-reader`, pure Rust (no libhdf5 on any machine; gzip/deflate and
//! shuffle filters included), read-only.
//!
//! Module map:
//! - [`read_hdf5`]: any supported file or directory; tells the two layouts apart.
//! - [`read_d4rl`]: D4RL's layout: top-level datasets `observations` `[N, obs_dim]`, `actions`
//!   `[N, act_dim]`, optional `terminals`, `timeouts` (`[N]`, bool or integer 0/1),
//!   `episode_starts` / `episode_lengths` and maze walls (`walls` / `wall_map` / `maze_map`),
//!   by the rules of [`crate::episodes`]. `rewards`, `infos/...` and everything else are left
//!   out (listed in [`Trajectories::ignored`]).
//! - [`read_minari`]: Minari's on-disk layout: `main_data.hdf5` (or a Minari dataset directory
//!   holding `data/main_data.hdf5`) with one group `episode_<id>` per episode, in id order.
//!   Each holds `observations` (`[T + 1, ...]`: the state after every action, plus the first),
//!   `actions` `[T, ...]`, `terminations` and `truncations` `[T]`. The last observation of an
//!   episode has no action and is dropped, so row k pairs a state with the action taken in it
//!   (D4RL's layout); each episode's first row is flagged in `episode_starts`.
//!
//! **Dict observations** (a group instead of a dataset, e.g. PointMaze's `achieved_goal`,
//! `desired_goal`, `observation`) are flattened the way gymnasium's `spaces.flatten` does for
//! a `Dict` space built from a plain dict: keys in sorted order, nested groups recursively,
//! each entry's trailing dimensions row-major, concatenated per row. PointMaze rows are
//! therefore `[achieved_goal (2), desired_goal (2), observation (4)]`. Dict actions are
//! refused (no environment we know of has them).
//!
//! Values are read as float32 (float64 data is rounded, as the server's training does); any
//! integer or float dtype in either byte order is accepted for values and flags, and h5py's
//! bool (an enum over int8) for flags.

use std::path::{Path, PathBuf};

use hdf5_reader::group::Group;
use hdf5_reader::{ByteOrder, Dataset, Datatype, Hdf5File};

use crate::episodes;
use crate::trajectories::Trajectories;

/// Why a file cannot be read: the file and what is wrong, naming the key or group.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct Hdf5Error {
    pub path: PathBuf,
    pub message: String,
}

pub type Result<T, E = Hdf5Error> = std::result::Result<T, E>;

/// Whether a path looks like HDF5 (by its signature) or a Minari dataset directory.
pub fn is_hdf5(path: &Path) -> bool {
    if path.is_dir() {
        return minari_file(path).is_some();
    }
    let mut magic = [0u8; 8];
    std::fs::File::open(path).and_then(|mut f| std::io::Read::read_exact(&mut f, &mut magic)).is_ok()
        && magic == *b"\x89HDF\r\n\x1a\n"
}

/// `dir/data/main_data.hdf5` or `dir/main_data.hdf5`, whichever exists.
fn minari_file(dir: &Path) -> Option<PathBuf> {
    [dir.join("data").join("main_data.hdf5"), dir.join("main_data.hdf5")].into_iter().find(|p| p.is_file())
}

/// A D4RL file or a Minari dataset: Minari when the root holds `episode_*` groups and no
/// `observations`, D4RL otherwise.
pub fn read_hdf5(path: &Path) -> Result<Trajectories> {
    let file_path = data_file(path)?;
    let (root, groups, datasets) = read_root(&file_path)?;
    if !datasets.iter().any(|d| d == "observations") && groups.iter().any(|g| g.starts_with("episode_")) {
        minari_from(&file_path, &root, &groups)
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
    let (root, groups, _) = read_root(&file_path)?;
    minari_from(&file_path, &root, &groups)
}

/// The HDF5 file a path names: the path itself, or a Minari directory's `main_data.hdf5`.
fn data_file(path: &Path) -> Result<PathBuf> {
    if path.is_dir() {
        minari_file(path).ok_or_else(|| err(path, "a directory without data/main_data.hdf5 (not a Minari dataset)"))
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

/// A numeric dataset as f64 with its shape and class. Errors name `key`.
fn numbers(ds: &Dataset, key: &str) -> std::result::Result<(Vec<u64>, Vec<f64>, Class), String> {
    let shape = ds.shape().to_vec();
    let (base, class) = match ds.dtype() {
        // h5py writes numpy bool as an enum FALSE = 0, TRUE = 1 over int8.
        Datatype::Enum { base, .. } => (base.as_ref().clone(), Class::Bool),
        other => (other.clone(), Class::Integer),
    };
    // (bytes per element, byte order, how to read one little-endian element)
    let (size, order, float) = match base {
        Datatype::FixedPoint { size, signed, byte_order } => {
            (usize::from(size), byte_order, if signed { Some(false) } else { None })
        }
        Datatype::FloatingPoint { size, byte_order } if size == 4 || size == 8 => {
            (usize::from(size), byte_order, Some(true))
        }
        other => return Err(format!("'{key}' has HDF5 type {other:?}; expected integers, floats or bool")),
    };
    if !matches!(size, 1 | 2 | 4 | 8) {
        return Err(format!("'{key}' has {size}-byte integers; expected 1, 2, 4 or 8"));
    }
    let class = match (class, float) {
        (Class::Bool, _) => Class::Bool,
        (_, Some(true)) => Class::Float,
        _ => Class::Integer,
    };
    let raw = ds.read_raw_bytes().map_err(|e| format!("'{key}': {e}"))?;
    let mut values = Vec::with_capacity(raw.len() / size);
    let mut b = [0u8; 8];
    for chunk in raw.chunks_exact(size) {
        b[..size].copy_from_slice(chunk);
        if order == ByteOrder::BigEndian {
            b[..size].reverse();
        }
        values.push(match (float, size) {
            (Some(true), 4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Some(true), _) => f64::from_le_bytes(b),
            (Some(false), 1) => f64::from(b[0] as i8),
            (Some(false), 2) => f64::from(i16::from_le_bytes([b[0], b[1]])),
            (Some(false), 4) => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Some(false), _) => i64::from_le_bytes(b) as f64,
            (None, 1) => f64::from(b[0]),
            (None, 2) => f64::from(u16::from_le_bytes([b[0], b[1]])),
            (None, 4) => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (None, _) => u64::from_le_bytes(b) as f64,
        });
    }
    Ok((shape, values, class))
}

/// `[N, d]` float values of a dataset (`[N]` is taken as `[N, 1]`, more dimensions are
/// flattened per row).
fn rows_of(ds: &Dataset, key: &str) -> std::result::Result<(usize, usize, Vec<f32>), String> {
    let (shape, values, class) = numbers(ds, key)?;
    if class == Class::Bool {
        return Err(format!("'{key}' is bool; expected numbers"));
    }
    let Some(&n) = shape.first() else { return Err(format!("'{key}' is a scalar; expected [N, dim]")) };
    let n = n as usize;
    let width = values.len().checked_div(n).unwrap_or(0);
    if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!("'{key}' holds a value that is not finite (element {bad})"));
    }
    Ok((n, width, values.iter().map(|&v| v as f32).collect()))
}

/// `[N]` flags of a dataset (bool or integer 0/1).
fn flags_of(ds: &Dataset, key: &str, rows: usize) -> std::result::Result<Vec<bool>, String> {
    let (shape, values, class) = numbers(ds, key)?;
    if shape.len() != 1 || shape[0] as usize != rows {
        return Err(format!("'{key}' has shape {shape:?}; episode flags must be [N] with N = {rows}"));
    }
    if class == Class::Float && values.iter().any(|&v| v != 0.0 && v != 1.0) {
        return Err(format!("'{key}' holds values other than 0 and 1; episode flags must be bool"));
    }
    Ok(values.iter().map(|&v| v != 0.0).collect())
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
    let (n, obs_dim, observations) = rows_of(&required("observations")?, "observations").map_err(e)?;
    let (na, act_dim, actions) = rows_of(&required("actions")?, "actions").map_err(e)?;
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
/// values)`. `at` names the place in errors.
fn flattened(group: &Group, name: &str, at: &str) -> std::result::Result<(usize, usize, Vec<f32>), String> {
    let (groups, datasets) = group.member_names().map_err(|e| format!("{at}: {e}"))?;
    if datasets.iter().any(|d| d == name) {
        let ds = group.dataset(name).map_err(|e| format!("{at}/{name}: {e}"))?;
        return rows_of(&ds, &format!("{at}/{name}"));
    }
    if !groups.iter().any(|g| g == name) {
        return Err(format!("no '{name}' in {at}"));
    }
    let sub = group.group(name).map_err(|e| format!("{at}/{name}: {e}"))?;
    let (mut keys_g, keys_d) = sub.member_names().map_err(|e| format!("{at}/{name}: {e}"))?;
    keys_g.extend(keys_d);
    keys_g.sort();
    if keys_g.is_empty() {
        return Err(format!("{at}/{name} is an empty group"));
    }
    let here = format!("{at}/{name}");
    let parts: Vec<(usize, usize, Vec<f32>)> =
        keys_g.iter().map(|k| flattened(&sub, k, &here)).collect::<std::result::Result<_, _>>()?;
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

fn minari_from(path: &Path, root: &Group, groups: &[String]) -> Result<Trajectories> {
    let e = |m: String| err(path, m);
    let mut episodes: Vec<(u64, &String)> = groups
        .iter()
        .filter_map(|g| g.strip_prefix("episode_").and_then(|id| id.parse::<u64>().ok()).map(|id| (id, g)))
        .collect();
    episodes.sort();
    if episodes.is_empty() {
        return Err(err(path, "no 'episode_<id>' groups (not a Minari main_data.hdf5)"));
    }
    let mut t = Trajectories::default();
    for (_, name) in &episodes {
        let ep = root.group(name).map_err(|x| err(path, format!("group '{name}': {x}")))?;
        let (_, ep_datasets) = ep.member_names().map_err(|x| err(path, format!("group '{name}': {x}")))?;
        if !ep_datasets.iter().any(|d| d == "actions") {
            return Err(err(path, format!("'{name}/actions' is missing or a group (dict actions are not supported)")));
        }
        let (steps, act_dim, actions) = flattened(&ep, "actions", name).map_err(e)?;
        let (n_obs, obs_dim, observations) = flattened(&ep, "observations", name).map_err(e)?;
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
        if steps == 0 {
            continue;
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
    t.ignored = vec!["rewards".to_owned(), "infos".to_owned()];
    Ok(t)
}
