//! The rules every reader (`.npz`, D4RL HDF5, Minari) uses to find episodes and maze walls in a
//! user's file. The Python package (`relreward.datasets`) applies the same rules; both are
//! documented in `docs/data-formats.md`.
//!
//! Module map:
//! - [`episode_starts_flags`]: an `episode_starts` array, either per-row flags or start
//!   indices, as per-row flags.
//! - [`flags_from_lengths`]: an `episode_lengths` array as per-row start flags.
//! - [`explicit_starts`]: both keys together (they must agree).
//! - [`pick_walls`]: the maze walls from `walls` / `wall_map` / `maze_map`.
//!
//! The rules, and why:
//! - **`episode_starts`, flags or indices.** A bool array is per-row flags. An integer array
//!   of N values (N = rows of `observations`) that are all 0 or 1 is per-row flags; any other
//!   integer array is a list of start row indices (strictly increasing, each in `[0, N)`).
//!   The two readings can only both fit a length-N array of 0s and 1s that is also strictly
//!   increasing, i.e. `[0]` or `[0, 1]`, and for those both readings give the same episodes
//!   (row 0 always starts one), so the rule is never ambiguous in effect. Float arrays are
//!   refused: a start is a row, not a measurement.
//! - **`episode_lengths`**: positive integers summing to N; episode k starts at the sum of the
//!   lengths before it.
//! - **Explicit boundaries beside flags.** When a file states its episodes explicitly
//!   (`episode_starts` as indices or `episode_lengths`), those episodes are sent as
//!   `episode_starts` flags, and `terminals` / `timeouts` are sent too: the server cuts an
//!   episode at either (an end flag and a start flag on the next row agree). A file whose
//!   flags contradict its index list is not detected here: both cut, which only splits
//!   episodes, never joins two.
//! - **Walls.** The first of `walls`, `wall_map`, `maze_map` present: a 2-D numeric array,
//!   nonzero = wall (D4RL's and gymnasium-robotics' `maze_map` write 1 for walls, 0 for free
//!   cells). When more than one is present they must agree, or the file is refused naming both.

/// Per-row start flags from an `episode_starts` array of `values` (as read, any numeric
/// dtype; `is_bool` when the array's dtype is bool) for a dataset of `rows` rows, and whether it
/// was read as indices. Errors name the key and say what is wrong.
pub fn episode_starts_flags(
    rows: usize,
    shape: &[u64],
    values: &[f64],
    is_bool: bool,
    is_integer: bool,
) -> Result<(Vec<bool>, bool), String> {
    const KEY: &str = "'episode_starts'";
    if shape.len() != 1 {
        return Err(format!("{KEY} has shape {shape:?}; expected 1-D (per-row flags [N] or start indices [K])"));
    }
    if is_bool {
        if values.len() != rows {
            return Err(format!("{KEY} holds {} flags but 'observations' has {rows} rows", values.len()));
        }
        return Ok((values.iter().map(|&v| v != 0.0).collect(), false));
    }
    if !is_integer {
        return Err(format!("{KEY} is a float array; it must be bool flags [N] or integer start indices [K]"));
    }
    if values.len() == rows && values.iter().all(|&v| v == 0.0 || v == 1.0) {
        return Ok((values.iter().map(|&v| v != 0.0).collect(), false));
    }
    flags_from_indices(rows, values).map(|f| (f, true))
}

/// Per-row start flags from a list of start row indices.
fn flags_from_indices(rows: usize, values: &[f64]) -> Result<Vec<bool>, String> {
    const KEY: &str = "'episode_starts'";
    let mut flags = vec![false; rows];
    let mut previous: Option<f64> = None;
    for (i, &v) in values.iter().enumerate() {
        if v < 0.0 || v >= rows as f64 || v.fract() != 0.0 {
            return Err(format!(
                "{KEY} read as start indices (integers, not all 0/1 or not one per row): entry {i} is {v}, \
                 outside [0, {rows}) of the {rows} rows"
            ));
        }
        if previous.is_some_and(|p| v <= p) {
            return Err(format!("{KEY} read as start indices: entry {i} ({v}) does not increase on the one before it"));
        }
        previous = Some(v);
        flags[v as usize] = true;
    }
    Ok(flags)
}

/// Per-row start flags from `episode_lengths` (positive integers summing to `rows`).
pub fn flags_from_lengths(rows: usize, shape: &[u64], values: &[f64], is_integer: bool) -> Result<Vec<bool>, String> {
    const KEY: &str = "'episode_lengths'";
    if shape.len() != 1 || !is_integer {
        return Err(format!("{KEY} must be a 1-D integer array (one length per episode); it has shape {shape:?}"));
    }
    let mut flags = vec![false; rows];
    let mut at = 0u64;
    for (i, &v) in values.iter().enumerate() {
        if v < 1.0 || v.fract() != 0.0 {
            return Err(format!("{KEY}: entry {i} is {v}; lengths must be positive integers"));
        }
        if at < rows as u64 {
            flags[at as usize] = true;
        }
        at = at.saturating_add(v as u64);
    }
    if at != rows as u64 {
        return Err(format!("{KEY} sum to {at} rows but 'observations' has {rows}"));
    }
    Ok(flags)
}

/// The explicit episode starts of a file: from `episode_starts` (flags or indices), from
/// `episode_lengths`, or both (they must give the same episodes). `None` when neither key is
/// present. The bool says whether the episodes came from an explicit list (indices or
/// lengths) rather than per-row flags.
pub fn explicit_starts(
    rows: usize,
    starts: Option<(&[u64], &[f64], bool, bool)>,
    lengths: Option<(&[u64], &[f64], bool)>,
) -> Result<Option<(Vec<bool>, bool)>, String> {
    let from_starts = starts
        .map(|(shape, values, is_bool, is_integer)| episode_starts_flags(rows, shape, values, is_bool, is_integer))
        .transpose()?;
    let from_lengths =
        lengths.map(|(shape, values, is_integer)| flags_from_lengths(rows, shape, values, is_integer)).transpose()?;
    match (from_starts, from_lengths) {
        (None, None) => Ok(None),
        (Some(s), None) => Ok(Some(s)),
        (None, Some(l)) => Ok(Some((l, true))),
        (Some((mut s, _)), Some(l)) => {
            // Row 0 always starts an episode, flagged or not.
            if let (Some(first), Some(_)) = (s.first_mut(), l.first()) {
                *first = true;
            }
            if s != l {
                let row = s.iter().zip(&l).position(|(a, b)| a != b).unwrap_or(0);
                return Err(format!(
                    "'episode_starts' and 'episode_lengths' disagree (first at row {row}); keep only one"
                ));
            }
            Ok(Some((l, true)))
        }
    }
}

/// Maze walls: `(rows, cols, wall flags row-major)`.
pub type Walls = (usize, usize, Vec<bool>);

/// The keys that may hold a maze's walls, in the order they are preferred.
pub const WALL_KEYS: [&str; 3] = ["walls", "wall_map", "maze_map"];

/// The walls from whichever of [`WALL_KEYS`] are present (`(key, shape, values)`), by the rule
/// in the module docs.
pub fn pick_walls(found: &[(&str, Vec<u64>, Vec<f64>)]) -> Result<Option<Walls>, String> {
    let mut chosen: Option<(&str, Walls)> = None;
    for (key, shape, values) in found {
        let &[rows, cols] = shape.as_slice() else {
            return Err(format!("'{key}' has shape {shape:?}; maze walls must be 2-D [rows, cols]"));
        };
        if values.iter().any(|v| !v.is_finite()) {
            return Err(format!("'{key}' holds a value that is not finite"));
        }
        let walls: Walls = (rows as usize, cols as usize, values.iter().map(|&v| v != 0.0).collect());
        match &chosen {
            None => chosen = Some((key, walls)),
            Some((first, w)) if *w != walls => {
                return Err(format!("'{first}' and '{key}' both give maze walls and they differ; keep only one"));
            }
            Some(_) => {}
        }
    }
    Ok(chosen.map(|(_, w)| w))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn starts(rows: usize, values: &[f64], is_bool: bool) -> Result<(Vec<bool>, bool), String> {
        episode_starts_flags(rows, &[values.len() as u64], values, is_bool, !is_bool)
    }

    #[test]
    fn integer_starts_of_zeros_and_ones_per_row_are_flags() {
        let (flags, indices) = starts(4, &[1.0, 0.0, 1.0, 0.0], false).expect("flags");
        assert_eq!(flags, [true, false, true, false]);
        assert!(!indices);
    }

    #[test]
    fn other_integer_starts_are_indices() {
        // The file: start indices beside per-row terminals/timeouts.
        let (flags, indices) = starts(6, &[0.0, 2.0, 5.0], false).expect("indices");
        assert_eq!(flags, [true, false, true, false, false, true]);
        assert!(indices);
        // N values that are not all 0/1: indices too.
        let (flags, _) = starts(3, &[0.0, 1.0, 2.0], false).expect("indices");
        assert_eq!(flags, [true, true, true]);
    }

    #[test]
    fn the_only_doubly_readable_arrays_mean_the_same_episodes() {
        // [0, 1] with N = 2: flags say "row 1 starts" (row 0 always does), indices say rows 0
        // and 1: the same two episodes.
        let (flags, _) = starts(2, &[0.0, 1.0], false).expect("flags");
        let indices = flags_from_indices(2, &[0.0, 1.0]).expect("indices");
        assert_eq!(&flags[1..], &indices[1..]);
    }

    #[test]
    fn bad_starts_are_refused_naming_the_key() {
        for (rows, values) in [(5, vec![0.0, 7.0]), (5, vec![0.0, 3.0, 3.0]), (5, vec![-1.0, 2.0])] {
            let err = starts(rows, &values, false).expect_err("bad");
            assert!(err.contains("'episode_starts'"), "{err}");
        }
        let err = episode_starts_flags(3, &[3], &[0.0, 1.5, 2.0], false, false).expect_err("float");
        assert!(err.contains("float"), "{err}");
        let err = starts(3, &[1.0, 0.0], true).expect_err("bool of wrong length");
        assert!(err.contains("3 rows"), "{err}");
    }

    #[test]
    fn lengths_make_starts_and_must_cover_every_row() {
        assert_eq!(flags_from_lengths(5, &[2], &[2.0, 3.0], true).expect("ok"), [true, false, true, false, false]);
        let err = flags_from_lengths(5, &[2], &[2.0, 2.0], true).expect_err("short");
        assert!(err.contains("'episode_lengths'") && err.contains("sum to 4"), "{err}");
        assert!(flags_from_lengths(5, &[2], &[0.0, 5.0], true).is_err());
    }

    #[test]
    fn starts_and_lengths_must_agree() {
        let s: (&[u64], &[f64], bool, bool) = (&[2], &[0.0, 2.0], false, true);
        let ok = explicit_starts(5, Some(s), Some((&[2], &[2.0, 3.0], true))).expect("agree");
        assert_eq!(ok, Some((vec![true, false, true, false, false], true)));
        let err = explicit_starts(5, Some(s), Some((&[2], &[3.0, 2.0], true))).expect_err("disagree");
        assert!(err.contains("'episode_starts' and 'episode_lengths'"), "{err}");
    }

    #[test]
    fn walls_come_from_any_known_key_and_must_agree() {
        let a = ("wall_map", vec![1, 2], vec![1.0, 0.0]);
        assert_eq!(pick_walls(std::slice::from_ref(&a)).expect("ok"), Some((1, 2, vec![true, false])));
        let b = ("maze_map", vec![1, 2], vec![0.0, 1.0]);
        let err = pick_walls(&[a.clone(), b]).expect_err("differ");
        assert!(err.contains("'wall_map' and 'maze_map'"), "{err}");
        let err = pick_walls(&[("walls", vec![4], vec![0.0; 4])]).expect_err("1-D");
        assert!(err.contains("'walls'"), "{err}");
        assert_eq!(pick_walls(&[]).expect("none"), None);
    }
}
