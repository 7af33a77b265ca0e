//! The (x, t) check every network's forward pass starts with (native and TorchScript
//! denoisers, reward networks), so that all of them refuse a bad input with the same message.

use tch::{Kind, Tensor};

use crate::engine::manifest::Conditioning;
use crate::error::{Error, Result};

/// Checks a network's inputs: `x` [B >= 1, *item_shape] of dtype `kind` and `t` int64 [B].
/// Messages start with `what` ("denoiser input x: ..."). Returns B.
pub fn check_inputs(what: &str, x: &Tensor, t: &Tensor, item_shape: &[i64], kind: Kind) -> Result<i64> {
    let size = x.size();
    let batch = size.first().copied().unwrap_or(0);
    if size.len() != item_shape.len() + 1 || batch < 1 || size[1..] != item_shape[..] {
        return Err(Error::invalid(format!(
            "{what} input x: shape {size:?} does not match [B >= 1, {}]",
            item_shape.iter().map(i64::to_string).collect::<Vec<_>>().join(", ")
        )));
    }
    let (x_kind, t_kind) = (x.f_kind()?, t.f_kind()?);
    if x_kind != kind {
        return Err(Error::invalid(format!("{what} input x: dtype {x_kind:?}, expected {}", dtype_name(kind))));
    }
    if t.size() != [batch] || t_kind != Kind::Int64 {
        return Err(Error::invalid(format!(
            "{what} input t: shape {:?} and dtype {t_kind:?}, expected int64 [{batch}]",
            t.size()
        )));
    }
    Ok(batch)
}

/// Checks a conditional network's `cond` for a batch of `batch` against the manifest's
/// `conditioning`: present exactly when the model is conditional; int64 `[B]` labels in
/// `0..num_classes` or float32 `[B, dim]` finite embeddings. Messages start with `what`.
pub fn check_condition(
    what: &str,
    cond: Option<&Tensor>,
    conditioning: Option<&Conditioning>,
    batch: i64,
) -> Result<()> {
    let (cond, conditioning) = match (cond, conditioning) {
        (None, None) => return Ok(()),
        (Some(_), None) => {
            return Err(Error::invalid(format!("{what} condition: given, but the model is unconditional")));
        }
        (None, Some(c)) => {
            return Err(Error::invalid(format!(
                "{what} condition: missing; the model is conditional ({})",
                describe(c)
            )));
        }
        (Some(cond), Some(c)) => (cond, c),
    };
    let (size, kind) = (cond.size(), cond.f_kind()?);
    match *conditioning {
        Conditioning::Labels { num_classes, .. } => {
            if size != [batch] || kind != Kind::Int64 {
                return Err(Error::invalid(format!(
                    "{what} condition: shape {size:?} and dtype {kind:?}, expected int64 labels [{batch}]"
                )));
            }
            let (lo, hi) = (cond.f_min()?.f_int64_value(&[])?, cond.f_max()?.f_int64_value(&[])?);
            if lo < 0 || hi >= num_classes as i64 {
                let bad = if lo < 0 { lo } else { hi };
                return Err(Error::invalid(format!("{what} condition: label {bad} is outside 0..{num_classes}")));
            }
        }
        Conditioning::Embedding { dim } => {
            if size != [batch, dim as i64] || kind != Kind::Float {
                return Err(Error::invalid(format!(
                    "{what} condition: shape {size:?} and dtype {kind:?}, expected float32 embeddings [{batch}, {dim}]"
                )));
            }
            if cond.f_isfinite()?.f_all()?.f_int64_value(&[])? != 1 {
                return Err(Error::invalid(format!("{what} condition: an embedding holds NaN or infinite values")));
            }
        }
    }
    Ok(())
}

/// A conditioning in words, for messages.
pub fn describe(c: &Conditioning) -> String {
    match *c {
        Conditioning::Labels { num_classes, null_class: Some(n) } => {
            format!("labels 0..{num_classes}, null label {n}")
        }
        Conditioning::Labels { num_classes, null_class: None } => format!("labels 0..{num_classes}, no null label"),
        Conditioning::Embedding { dim } => format!("embeddings of width {dim}"),
    }
}

/// A dtype by both of its names, the wire's and libtorch's ("float32 (Float)"), as the
/// denoisers' and the reward networks' messages gave them before they shared this check.
fn dtype_name(kind: Kind) -> String {
    match kind {
        Kind::Float => "float32 (Float)".to_string(),
        Kind::Double => "float64 (Double)".to_string(),
        other => format!("{other:?}"),
    }
}
