//! The (x, t) check every network's forward pass starts with (native and TorchScript
//! denoisers, reward networks), so that all of them refuse a bad input with the same message.

use tch::{Kind, Tensor};

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

/// A dtype by both of its names, the wire's and libtorch's ("float32 (Float)"), as the
/// denoisers' and the reward networks' messages gave them before they shared this check.
fn dtype_name(kind: Kind) -> String {
    match kind {
        Kind::Float => "float32 (Float)".to_string(),
        Kind::Double => "float64 (Double)".to_string(),
        other => format!("{other:?}"),
    }
}
