//! What a relative reward network is, before anything is allocated: [`RewardArchitecture`]
//! (the serialized choice, as stored in job specs and reward manifests; defined in the shared
//! schema) and [`Plan`], its
//! hyperparameters in i64 validated against the item shape, with the parameter count computed
//! without allocating, and [`Network`], the layers it builds. Each architecture's own rules
//! live in its file ([`super::windowed_mlp`], [`super::value_function`],
//! [`super::conv_encoder`], [`super::mlp`]); this file dispatches to them.

use tch::nn;

use super::checks::shape_text;
use super::conv_encoder::{ConvEncoderNet, ConvEncoderPlan};
use super::mlp::{MlpNet, MlpPlan};
use super::value_function::{ValueFunctionNet, ValueFunctionPlan};
use super::windowed_mlp::{WindowedMlpNet, WindowedMlpPlan};
use crate::engine::nets::mlp::MAX_FEATURES;
use crate::engine::nets::native::MAX_PARAMETERS;
use crate::error::{Error, Result};

/// The architecture of a relative reward network: the shared schema's type (its kinds, widths
/// and defaults are `relreward_proto::schema::job`'s); this file plans and builds it.
pub use relreward_proto::schema::job::RewardArchitecture;

/// The layers of one architecture (the variables live in the `RewardNet`'s `Weights`).
#[derive(Debug)]
pub(super) enum Network {
    WindowedMlp(WindowedMlpNet),
    ValueFunction(Box<ValueFunctionNet>),
    ConvEncoder(Box<ConvEncoderNet>),
    Mlp(MlpNet),
}

/// The hyperparameters in i64, validated against the item shape.
#[derive(Debug, Clone)]
pub(super) enum Plan {
    WindowedMlp(WindowedMlpPlan),
    ValueFunction(ValueFunctionPlan),
    ConvEncoder(ConvEncoderPlan),
    Mlp(MlpPlan),
}

impl Plan {
    pub(super) fn new(architecture: &RewardArchitecture, item_shape: &[i64]) -> Result<Self> {
        if item_shape.is_empty() || item_shape.iter().any(|&d| d <= 0) {
            return Err(Error::invalid(format!(
                "item shape: [{}] must be non-empty with positive dimensions",
                shape_text(item_shape)
            )));
        }
        let features =
            item_shape.iter().try_fold(1i64, |acc, &d| acc.checked_mul(d)).filter(|&n| n <= MAX_FEATURES).ok_or_else(
                || {
                    Error::invalid(format!(
                        "item shape: [{}] has more than {MAX_FEATURES} elements",
                        shape_text(item_shape)
                    ))
                },
            )?;
        Ok(match architecture {
            RewardArchitecture::WindowedMlp { window, hidden } => {
                Self::WindowedMlp(WindowedMlpPlan::new(item_shape, *window, hidden)?)
            }
            RewardArchitecture::ValueFunction { widths } => {
                Self::ValueFunction(ValueFunctionPlan::new(item_shape, widths)?)
            }
            RewardArchitecture::ConvEncoder { widths } => Self::ConvEncoder(ConvEncoderPlan::new(item_shape, widths)?),
            RewardArchitecture::Mlp { hidden } => Self::Mlp(MlpPlan::new(features, hidden)?),
        })
    }

    /// Number of parameters, within [`MAX_PARAMETERS`], computed without allocating.
    pub(super) fn params(&self) -> Result<u64> {
        let count = match self {
            Self::WindowedMlp(plan) => plan.params(),
            Self::ValueFunction(plan) => plan.params(),
            Self::ConvEncoder(plan) => plan.params(),
            Self::Mlp(plan) => plan.params(),
        };
        if count > u128::from(MAX_PARAMETERS) {
            return Err(Error::invalid(format!(
                "architecture: {count} parameters exceed the limit of {MAX_PARAMETERS}"
            )));
        }
        u64::try_from(count).map_err(|_| Error::invalid("architecture: too many parameters"))
    }

    /// The network's layers, their variables created under `root` (PyTorch's module names).
    pub(super) fn build(&self, root: &nn::Path) -> Result<Network> {
        Ok(match self {
            Self::WindowedMlp(plan) => Network::WindowedMlp(plan.build(root)?),
            Self::ValueFunction(plan) => Network::ValueFunction(Box::new(plan.build(root)?)),
            Self::ConvEncoder(plan) => Network::ConvEncoder(Box::new(plan.build(root)?)),
            Self::Mlp(plan) => Network::Mlp(plan.build(root)?),
        })
    }
}
