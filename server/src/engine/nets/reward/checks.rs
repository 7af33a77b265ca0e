//! The hyperparameter checks the reward architectures share: sizes into i64, hidden and
//! convolutional widths, trajectory item shapes, parameter arithmetic. Errors name the field.

use crate::engine::nets::blocks::GROUPS;
use crate::engine::nets::mlp::{MAX_HIDDEN, MAX_LAYERS};
use crate::engine::nets::temporal_unet::{MAX_LEVELS, MAX_WIDTH};
use crate::error::{Error, Result};

pub(super) fn to_i64(value: usize, field: &str) -> Result<i64> {
    i64::try_from(value).map_err(|_| Error::invalid(format!("{field}: {value} is too large")))
}

fn to_i64s(values: &[usize], field: &str) -> Result<Vec<i64>> {
    values.iter().map(|&v| to_i64(v, field)).collect()
}

pub(super) fn shape_text(shape: &[i64]) -> String {
    shape.iter().map(i64::to_string).collect::<Vec<_>>().join(", ")
}

/// Number of parameters as a u128 (for arithmetic that must not overflow).
pub(super) fn count(x: i64) -> u128 {
    u128::try_from(x.max(0)).unwrap_or(0)
}

/// Hidden widths of the MLP architectures: 1 to [`MAX_LAYERS`] widths in 1..=[`MAX_HIDDEN`].
pub(super) fn validate_hidden(hidden: &[usize]) -> Result<Vec<i64>> {
    let hidden = to_i64s(hidden, "architecture.hidden")?;
    if hidden.is_empty() || hidden.len() > MAX_LAYERS || hidden.iter().any(|&h| h <= 0 || h > MAX_HIDDEN) {
        return Err(Error::invalid(format!(
            "architecture.hidden: {hidden:?} must hold 1 to {MAX_LAYERS} widths in 1..={MAX_HIDDEN}"
        )));
    }
    Ok(hidden)
}

/// Widths of the convolutional architectures: 1 to [`MAX_LEVELS`] positive multiples of 8.
pub(super) fn validate_widths(widths: &[usize]) -> Result<Vec<i64>> {
    let widths = to_i64s(widths, "architecture.widths")?;
    if widths.is_empty() || widths.len() > MAX_LEVELS {
        return Err(Error::invalid(format!("architecture.widths: {widths:?} must hold 1 to {MAX_LEVELS} widths")));
    }
    if let Some(w) = widths.iter().find(|&&w| w <= 0 || w % GROUPS != 0 || w > MAX_WIDTH) {
        return Err(Error::invalid(format!(
            "architecture.widths: {w} in {widths:?} must be a positive multiple of {GROUPS} (GroupNorm with {GROUPS} groups) up to {MAX_WIDTH}"
        )));
    }
    Ok(widths)
}

pub(super) fn trajectory_shape(item_shape: &[i64], kind: &str) -> Result<(i64, i64)> {
    match item_shape {
        &[horizon, transition_dim] => Ok((horizon, transition_dim)),
        _ => Err(Error::invalid(format!(
            "architecture: {kind} needs a trajectory item shape [horizon, transition_dim], got [{}]",
            shape_text(item_shape)
        ))),
    }
}
