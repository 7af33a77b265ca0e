//! One place that validates a reward query. Score, Gradient and GradientStream (from their
//! relreward.v1 messages: [`Query::score`], [`Query::gradient`]) and OIP ModelInfer (from the
//! inputs `api::oip` parsed out of the protocol's tensors) all become a [`Query`], and
//! [`Serving::prepare`] checks it against its model, in this order, before any compute:
//!
//! 1. at the door, the wire: `x` decodes as float32 or float64 (a finite float64 that float32
//!    cannot hold is refused here, before it becomes an infinity), enum values are known
//!    ([`Units::from_wire`]);
//! 2. the model: its name ([`crate::fields::validate_name`], in [`Serving::reward`]), then a
//!    reward or discriminator model that loads;
//! 3. `x`'s shape `[B, *item_shape]` with 1 <= B <= `serving.max_request_items`, its values
//!    filling it, each finite;
//! 4. `t`: none, one for every item, or one per item, each in [0, T);
//! 5. the operation: per-step values need a windowed reward; a gradient's `omega`
//!    ([`crate::fields::check_omega`]) and the diffusion model whose posterior variance
//!    scales it;
//! 6. units: raw inputs are normalized on their own float32 values (the normalizer's float32
//!    arithmetic, without a tensor), and a fitted normalizer's inputs must then lie within
//!    [`MAX_NORMALIZED_X`].
//!
//! Every error is INVALID_ARGUMENT naming the field (`x`, `t`, `per_step`, `omega`, ...),
//! except the model's own NOT_FOUND, FAILED_PRECONDITION and DATA_LOSS. After compute,
//! [`check_finite`] refuses any answer that is not finite.

use std::time::Instant;

use relreward_proto::tensor;
use relreward_proto::v1 as pb;

use super::{Answer, Serving};
use crate::engine::normalizer::Normalize;
use crate::error::{Error, Result, brief};
use crate::fields;
use crate::registry::SharedReward;

/// Queries of one kind can share a forward pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchKind {
    Score { per_window: bool, per_step: bool },
    Gradient,
}

/// Largest |x| accepted in the model's normalized units. The normalizer maps the training data
/// to about [-1, 1] (limits) or to z-scores (gaussian), and a noisy x_t stays within a few
/// units of that; values beyond this bound are far outside anything the model has seen and
/// only make rho overflow.
pub const MAX_NORMALIZED_X: f64 = 1e4;

/// Units of inputs and gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Units {
    /// The dataset's units (the default everywhere).
    Raw,
    /// The diffusion models' normalized units, which rho takes.
    Normalized,
}

/// What to compute for a query.
#[derive(Debug, Clone, PartialEq)]
pub enum Op {
    /// rho, and optionally per-window and per-step values.
    Score { per_window: bool, per_step: bool },
    /// rho and grad_x rho in `units`, times `omega` and, when given, times the posterior
    /// variance of the named diffusion model's schedule at each item's t.
    Gradient { units: Units, omega: f64, variance_of: Option<String> },
}

/// A query as it arrives from either protocol: `values` holds `shape` row-major.
#[derive(Debug)]
pub struct Query {
    pub shape: Vec<i64>,
    pub values: Vec<f32>,
    /// Empty: t = 0 for all items; one value: broadcast; else one per item.
    pub t: Vec<i64>,
    pub input_units: Units,
    pub op: Op,
    /// The caller's deadline (gRPC `grpc-timeout`).
    pub deadline: Option<Instant>,
}

impl Units {
    /// A `Units` enum field from the wire (`field` names it): unspecified means raw.
    pub fn from_wire(field: &str, raw: i32) -> Result<Self> {
        Ok(match fields::known(field, raw, "UNITS_RAW (the default) or UNITS_NORMALIZED")? {
            pb::Units::Unspecified | pb::Units::Raw => Self::Raw,
            pb::Units::Normalized => Self::Normalized,
        })
    }
}

impl Query {
    /// A Score request as a query.
    pub fn score(req: &pb::ScoreRequest, deadline: Option<Instant>) -> Result<Self> {
        let (shape, values) = decode_x("x", req.x.as_ref())?;
        Ok(Self {
            shape,
            values,
            t: times(&req.t),
            input_units: Units::from_wire("input_units", req.input_units)?,
            op: Op::Score { per_window: req.per_window, per_step: req.per_step },
            deadline,
        })
    }

    /// A Gradient request (alone or one of a GradientStream) as a query: omega 1 unless
    /// given; no variance scaling unless a diffusion model is named.
    pub fn gradient(req: &pb::GradientRequest, deadline: Option<Instant>) -> Result<Self> {
        let (shape, values) = decode_x("x", req.x.as_ref())?;
        let variance_of =
            (!req.scale_by_posterior_variance_of.is_empty()).then(|| req.scale_by_posterior_variance_of.clone());
        Ok(Self {
            shape,
            values,
            t: times(&req.t),
            input_units: Units::from_wire("input_units", req.input_units)?,
            op: Op::Gradient {
                units: Units::from_wire("gradient_units", req.gradient_units)?,
                omega: req.omega.unwrap_or(1.0),
                variance_of,
            },
            deadline,
        })
    }
}

/// The shape and float32 values of a float32 or float64 tensor field (finiteness is checked
/// by [`Serving::prepare`], with the element's index).
fn decode_x(field: &str, x: Option<&pb::Tensor>) -> Result<(Vec<i64>, Vec<f32>)> {
    let x = x.ok_or_else(|| Error::invalid(format!("{field}: missing")))?;
    // Sized for float32 (float64 needs half): one allocation per request, not a doubling series.
    let mut values = Vec::with_capacity(x.data.len() / 4);
    // NaN and infinities are refused later with their element (prepare); a finite float64
    // that float32 cannot hold is refused here, before it becomes an infinity.
    let mut overflow = None;
    tensor::for_each_float(x, |v| {
        if overflow.is_none() && tensor::beyond_f32(v) {
            overflow = Some((values.len(), v));
        }
        values.push(v as f32);
    })
    .map_err(|e| Error::invalid(format!("{field}: {e}")))?;
    if let Some((i, v)) = overflow {
        return Err(Error::invalid(format!("{field}: element {i} ({v:e}) is {}", tensor::OUTSIDE_F32)));
    }
    let shape = x
        .shape
        .iter()
        .map(|&d| i64::try_from(d).map_err(|_| Error::invalid(format!("{field}: dimension {d} is too large"))))
        .collect::<Result<Vec<_>>>()?;
    Ok((shape, values))
}

fn times(t: &[u32]) -> Vec<i64> {
    t.iter().map(|&v| i64::from(v)).collect()
}

/// A validated query, ready for the batcher.
#[derive(Debug)]
pub struct Prepared {
    pub(super) model: SharedReward,
    /// `[B, *item_shape]` row-major, float32, in normalized units.
    pub(super) x: Vec<f32>,
    /// `[B]`.
    pub(super) t: Vec<i64>,
    pub(super) kind: BatchKind,
    /// Per-item gradient factor `[B]` (omega times posterior variance), with the Jacobian to
    /// apply for raw-unit gradients.
    pub(super) gradient_post: Option<GradientPost>,
    pub(super) deadline: Option<Instant>,
}

#[derive(Debug)]
pub(super) struct GradientPost {
    /// `[B]`; `None` when every factor is exactly 1 (omega unset or 1, no variance scaling:
    /// the planner's common case), which saves a multiply per query.
    pub(super) factor: Option<Vec<f32>>,
    pub(super) raw_units: bool,
}

impl Prepared {
    pub fn batch(&self) -> i64 {
        self.t.len() as i64
    }
}

impl Serving {
    /// Validates `query` against `model` (steps 3 to 6 of the module's order) and converts it
    /// to normalized float32 values. Costs no model compute and no libtorch call; every error
    /// names the field (`x`, `t`, `per_step`, ...).
    pub async fn prepare(&self, model: SharedReward, query: Query) -> Result<Prepared> {
        let item = &model.item_shape;
        let n_items = check_shape(&query.shape, item, self.inner.config.max_request_items)?;
        if query.values.len() != n_items * item.iter().product::<i64>() as usize {
            return Err(Error::invalid(format!(
                "x: {} values do not fill the shape {}",
                query.values.len(),
                brief(&query.shape)
            )));
        }
        if let Some(i) = query.values.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(format!("x: element {i} is not finite ({})", query.values[i])));
        }
        let big_t = model.manifest.n_timesteps as i64;
        let t = broadcast_t(&query.t, n_items, big_t)?;
        let kind = match &query.op {
            Op::Score { per_window, per_step } => {
                if *per_step && model.window.is_none() {
                    return Err(Error::invalid(format!(
                        "per_step: model '{}' is not windowed ({}); per-step values need a windowed_mlp reward",
                        model.name, model.manifest.architecture
                    )));
                }
                BatchKind::Score { per_window: *per_window, per_step: *per_step }
            }
            Op::Gradient { .. } => BatchKind::Gradient,
        };
        let gradient_post = match &query.op {
            Op::Score { .. } => None,
            Op::Gradient { units, omega, variance_of } => {
                fields::check_omega(*omega)?;
                let mut factor = vec![*omega; n_items];
                if let Some(base) = variance_of {
                    let variance = self.posterior_variance(base, big_t).await?;
                    for (f, &ti) in factor.iter_mut().zip(&t) {
                        *f *= variance[ti as usize];
                    }
                }
                let factor =
                    (!factor.iter().all(|&f| f == 1.0)).then(|| factor.iter().map(|&f| f as f32).collect::<Vec<_>>());
                Some(GradientPost { factor, raw_units: *units == Units::Raw })
            }
        };
        let identity = model.manifest.normalizer == crate::engine::normalizer::Normalizer::Identity;
        let x = match query.input_units {
            Units::Normalized => query.values,
            Units::Raw if identity => query.values,
            Units::Raw => {
                let mut values = query.values;
                model.manifest.normalizer.normalize_values(&mut values);
                values
            }
        };
        // Only a normalizer fitted to data says what range is meaningful; with identity, the
        // results' own finiteness is the check.
        if !identity {
            check_normalized_range("x", &x, query.input_units)?;
        }
        Ok(Prepared { model, x, t, kind, gradient_post, deadline: query.deadline })
    }
}

/// Refuses normalized inputs beyond [`MAX_NORMALIZED_X`], naming `field`, its first such
/// element and the units it was given in (Score and Gradient's `x`, Sample's condition states).
pub(crate) fn check_normalized_range(field: &str, x: &[f32], units: Units) -> Result<()> {
    let Some(first) = x.iter().position(|v| v.is_nan() || f64::from(v.abs()) > MAX_NORMALIZED_X) else {
        return Ok(());
    };
    let value = x[first];
    let given = match units {
        Units::Raw => "after normalizing the raw input",
        Units::Normalized => "as given (input_units normalized)",
    };
    Err(Error::invalid(format!(
        "{field}: element {first} is {value:e} in the model's normalized units ({given}), outside the accepted \
         [-{MAX_NORMALIZED_X:e}, {MAX_NORMALIZED_X:e}]; the normalizer maps the training data to about [-1, 1], so \
         check the input's units and scale"
    )))
}

/// An answer must never carry Inf or NaN: inputs inside the accepted ranges that still
/// overflow the model are refused rather than answered.
pub(super) fn check_finite(answer: &Answer) -> Result<()> {
    let parts = [("rewards", Some(&answer.rewards)), ("gradient", answer.gradient.as_ref())];
    let parts =
        parts.into_iter().chain([("per_window", answer.per_window.as_ref()), ("per_step", answer.per_step.as_ref())]);
    for (what, host) in parts {
        let Some(host) = host else { continue };
        if !host.values.iter().all(|v| v.is_finite()) {
            return Err(Error::invalid(format!(
                "x: the model's {what} for these inputs is not finite (the inputs or omega are too large for it); \
                 nothing was returned"
            )));
        }
    }
    Ok(())
}

/// Checks `shape` = [B, *item] with 1 <= B <= max; returns B.
fn check_shape(shape: &[i64], item: &[i64], max: usize) -> Result<usize> {
    if shape.len() != item.len() + 1 || shape[1..] != *item {
        let mut want = vec!["B".to_owned()];
        want.extend(item.iter().map(i64::to_string));
        return Err(Error::invalid(format!(
            "x: expected shape [{}] for this model, got {}",
            want.join(", "),
            brief(&shape)
        )));
    }
    let b = shape[0];
    if b < 1 {
        return Err(Error::invalid("x: the batch is empty (B = 0); send at least one item"));
    }
    if b as usize > max {
        return Err(Error::invalid(format!(
            "x: {b} items is above the limit of {max} per request (serving.max_request_items); split the batch"
        )));
    }
    Ok(b as usize)
}

/// t per item: empty means 0, one value is broadcast, else exactly B values in [0, T).
fn broadcast_t(t: &[i64], b: usize, big_t: i64) -> Result<Vec<i64>> {
    let t = match t.len() {
        0 => vec![0; b],
        1 => vec![t[0]; b],
        n if n == b => t.to_vec(),
        n => return Err(Error::invalid(format!("t: {n} values for {b} items (give none, one, or one per item)"))),
    };
    // The field is named only for the first bad value (no formatting on the hot path).
    if let Some((i, &v)) = t.iter().enumerate().find(|(_, v)| !(0..big_t).contains(*v)) {
        fields::diffusion_time(&format!("t[{i}]"), v, big_t as usize)?;
    }
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_and_times_are_checked_with_named_fields() {
        assert_eq!(check_shape(&[3, 4, 2], &[4, 2], 10).expect("ok"), 3);
        let e = check_shape(&[3, 4], &[4, 2], 10).unwrap_err().to_string();
        assert!(e.contains("x: expected shape [B, 4, 2]") && e.contains("[3, 4]"), "{e}");
        assert!(check_shape(&[0, 4, 2], &[4, 2], 10).unwrap_err().to_string().contains("B = 0"));
        assert!(check_shape(&[11, 4, 2], &[4, 2], 10).unwrap_err().to_string().contains("max_request_items"));
        assert_eq!(broadcast_t(&[], 2, 10).expect("zeros"), [0, 0]);
        assert_eq!(broadcast_t(&[3], 2, 10).expect("broadcast"), [3, 3]);
        assert!(broadcast_t(&[1, 2, 3], 2, 10).unwrap_err().to_string().contains("t: 3 values for 2 items"));
        assert!(broadcast_t(&[1, 10], 2, 10).unwrap_err().to_string().contains("t[1]: 10 is outside [0, 10)"));
        assert!(broadcast_t(&[-1], 2, 10).unwrap_err().to_string().contains("t[0]: -1"));
    }
}
