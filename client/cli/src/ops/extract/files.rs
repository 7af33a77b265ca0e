//! A run's files: recordings in any supported form read and, when they must be converted
//! (HDF5, Minari) or padded (absorbing terminal states), written as the canonical `.npz` the
//! rest of the run reads; the fingerprints and name parts that name a run's datasets.

use std::collections::hash_map::DefaultHasher;
use std::hash::{Hash, Hasher};
use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use relreward_toolkit::trajectories::Trajectories;

use crate::UsageError;
use crate::output::eprint_line;

/// A name part made of the allowed characters (`[a-z0-9._-]`), at most `max` long.
pub fn slug(text: &str, max: usize) -> String {
    let s: String = text
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' })
        .collect::<String>()
        .trim_matches('-')
        .chars()
        .take(max)
        .collect::<String>()
        .trim_end_matches('-')
        .to_owned();
    if s.is_empty() { "data".into() } else { s }
}

/// A fingerprint of a file's bytes (for names, not security: the std hasher, stable within
/// a build).
pub fn file_fingerprint(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).with_context(|| format!("{}", path.display()))?;
    let mut h = DefaultHasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        buf[..n].hash(&mut h);
    }
    Ok(format!("{:08x}", h.finish() as u32))
}

/// Reads any supported file; HDF5 and Minari inputs are written as `.npz` into `data_dir`.
/// Returns the `.npz` to use and the data.
/// With `absorbing > 0`, terminal states are padded ([`Trajectories::absorb_terminals`], the
/// `at_rest` columns zeroed, found by [`Trajectories::velocity_columns`] when `None`) and the
/// result written there too.
pub fn canonical(
    path: &Path,
    data_dir: &Path,
    label: &str,
    absorbing: usize,
    at_rest: Option<&[usize]>,
) -> Result<(PathBuf, Trajectories)> {
    let hdf5 = relreward_toolkit::hdf5::is_hdf5(path);
    let mut t = if hdf5 { relreward_toolkit::hdf5::read_hdf5(path)? } else { Trajectories::from_npz(path)? };
    for note in &t.notes {
        eprint_line(&format!("{label}: {note}"));
    }
    let padded = absorbing > 0 && t.terminals.iter().any(|&b| b);
    if padded {
        let columns = match at_rest {
            Some(c) => {
                if let Some(&bad) = c.iter().find(|&&j| j >= t.obs_dim) {
                    bail!(UsageError(format!(
                        "--velocity-columns: column {bad} is out of range; observations have {} columns",
                        t.obs_dim
                    )));
                }
                c.to_vec()
            }
            None => t.velocity_columns(),
        };
        eprint_line(&format!(
            "{label}: terminal states held {absorbing} rows at rest in observation columns {columns:?}"
        ));
        t.absorb_terminals(absorbing, &columns);
    }
    if hdf5 || padded {
        let dest = data_dir.join(format!("{label}.npz"));
        t.write_npz(&dest).with_context(|| format!("writing {}", dest.display()))?;
        Ok((dest, t))
    } else {
        Ok((path.to_owned(), t))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_made_of_allowed_characters() {
        assert_eq!(slug("PointMaze_UMaze-v3 (goal 1)", 16), "pointmaze-umaze");
        assert_eq!(slug("!!!", 8), "data");
    }
}
