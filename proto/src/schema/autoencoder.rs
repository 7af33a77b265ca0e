//! The autoencoder manifest (`relreward.v1.AutoencoderUploadManifest`, issue 37 item 3): the
//! contract between an uploaded TorchScript encoder/decoder and the service, in the three forms
//! every document here has (the file `relreward model upload --autoencoder` reads, the record
//! the server stores as `manifest.json`, the wire message), with its defaults and its one check.
//!
//! ```toml
//! image_shape = [3, 16, 16]   # one image, what encode takes
//! latent_shape = [4, 4, 4]    # one latent, what encode returns and decode takes
//! scaling_factor = 0.18215    # diffusers' vae.config.scaling_factor; default 1
//! shift_factor = 0.0          # diffusers' vae.config.shift_factor (SD3, Flux); default 0
//! ```
//!
//! The service's latents are diffusers' scaled ones: `(encode(x) - shift) * scale`, and
//! `decode(z / scale + shift)` (see the proto for the module's methods).

use serde::{Deserialize, Serialize};

use super::{Invalid, invalid};
use crate::given_number;
use crate::v1 as pb;

/// `scaling_factor` when none is given: latents as the encoder returns them.
pub const DEFAULT_SCALING_FACTOR: f64 = 1.0;
/// `shift_factor` when none is given.
pub const DEFAULT_SHIFT_FACTOR: f64 = 0.0;
/// Most elements in one image or one latent (2^28 float32 values, 1 GiB): far above any
/// autoencoder this service runs, low enough that the upload's zeros probe stays small.
pub const MAX_ITEM_ELEMENTS: u64 = 1 << 28;

fn default_scaling_factor() -> f64 {
    DEFAULT_SCALING_FACTOR
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoencoderManifest {
    pub image_shape: Vec<usize>,
    pub latent_shape: Vec<usize>,
    #[serde(default = "default_scaling_factor")]
    pub scaling_factor: f64,
    #[serde(default)]
    pub shift_factor: f64,
}

impl AutoencoderManifest {
    /// Parses a manifest file, TOML or JSON, and validates it.
    pub fn parse(text: &str, name: Option<&str>) -> Result<Self, Invalid> {
        let format = super::Format::guess(name, text);
        let m: Self = super::parse_text(text, format, name.unwrap_or("autoencoder manifest"))?;
        m.validate_at("autoencoder manifest")?;
        Ok(m)
    }

    /// Both shapes non-empty with positive dimensions and at most [`MAX_ITEM_ELEMENTS`]
    /// elements, the scaling factor finite and positive, the shift finite; messages name
    /// `field.*`.
    pub fn validate_at(&self, field: &str) -> Result<(), Invalid> {
        check_shape(&format!("{field}.image_shape"), &self.image_shape)?;
        check_shape(&format!("{field}.latent_shape"), &self.latent_shape)?;
        let s = self.scaling_factor;
        if !(s.is_finite() && s > 0.0) {
            return invalid(format!(
                "{field}.scaling_factor: {} must be finite and positive (diffusers' vae.config.scaling_factor; 1 \
                 for latents as the encoder returns them)",
                given_number(s)
            ));
        }
        if !self.shift_factor.is_finite() {
            return invalid(format!("{field}.shift_factor: {} is not finite", given_number(self.shift_factor)));
        }
        Ok(())
    }

    /// One image's shape as tch sizes.
    pub fn image_sizes(&self) -> Vec<i64> {
        self.image_shape.iter().map(|&d| d as i64).collect()
    }

    /// One latent's shape as tch sizes.
    pub fn latent_sizes(&self) -> Vec<i64> {
        self.latent_shape.iter().map(|&d| d as i64).collect()
    }

    pub fn to_proto(&self) -> pb::AutoencoderUploadManifest {
        pb::AutoencoderUploadManifest {
            image_shape: self.image_shape.iter().map(|&d| d as u64).collect(),
            latent_shape: self.latent_shape.iter().map(|&d| d as u64).collect(),
            scaling_factor: Some(self.scaling_factor),
            shift_factor: Some(self.shift_factor),
        }
    }

    /// What `Model.autoencoder` reports.
    pub fn to_info(&self) -> pb::AutoencoderInfo {
        pb::AutoencoderInfo {
            image_shape: self.image_shape.iter().map(|&d| d as u64).collect(),
            latent_shape: self.latent_shape.iter().map(|&d| d as u64).collect(),
            scaling_factor: self.scaling_factor,
            shift_factor: self.shift_factor,
        }
    }

    /// From the wire, defaults filled and validated; `field` is the manifest's path in the
    /// request ("header.autoencoder") and every message names the field below it.
    pub fn from_proto(m: pb::AutoencoderUploadManifest, field: &str) -> Result<Self, Invalid> {
        let shape = |name: &str, v: &[u64]| -> Result<Vec<usize>, Invalid> {
            v.iter()
                .map(|&d| usize::try_from(d).map_err(|_| Invalid(format!("{field}.{name}: {d} is too large"))))
                .collect()
        };
        let manifest = Self {
            image_shape: shape("image_shape", &m.image_shape)?,
            latent_shape: shape("latent_shape", &m.latent_shape)?,
            scaling_factor: m.scaling_factor.unwrap_or(DEFAULT_SCALING_FACTOR),
            shift_factor: m.shift_factor.unwrap_or(DEFAULT_SHIFT_FACTOR),
        };
        manifest.validate_at(field)?;
        Ok(manifest)
    }
}

fn check_shape(field: &str, shape: &[usize]) -> Result<(), Invalid> {
    if shape.is_empty() {
        return invalid(format!("{field}: missing; one item's shape, e.g. [C, H, W]"));
    }
    if shape.contains(&0) {
        return invalid(format!("{field}: {shape:?} has a zero dimension; every dimension must be positive"));
    }
    let elements = shape.iter().try_fold(1u64, |acc, &d| acc.checked_mul(d as u64));
    if elements.is_none_or(|n| n > MAX_ITEM_ELEMENTS) {
        return invalid(format!("{field}: {shape:?} has more than {MAX_ITEM_ELEMENTS} elements per item"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn autoencoder_manifest_defaults_round_trip_and_name_fields() {
        let m = AutoencoderManifest::parse("image_shape = [1, 8, 8]\nlatent_shape = [2, 2, 2]\n", Some("a.toml"))
            .expect("parses");
        assert_eq!((m.scaling_factor, m.shift_factor), (1.0, 0.0));
        assert_eq!(AutoencoderManifest::from_proto(m.to_proto(), "header.autoencoder").expect("wire"), m);
        let json = serde_json::to_string(&m).expect("json");
        assert_eq!(AutoencoderManifest::parse(&json, None).expect("json parses"), m);
        let defaults = pb::AutoencoderUploadManifest {
            image_shape: vec![1, 8, 8],
            latent_shape: vec![2, 2, 2],
            ..Default::default()
        };
        assert_eq!(AutoencoderManifest::from_proto(defaults, "h").expect("defaults"), m);

        let cases: Vec<(pb::AutoencoderUploadManifest, &str)> = vec![
            (pb::AutoencoderUploadManifest { image_shape: vec![], ..m.to_proto() }, "h.image_shape: missing"),
            (pb::AutoencoderUploadManifest { latent_shape: vec![4, 0], ..m.to_proto() }, "h.latent_shape: [4, 0]"),
            (
                pb::AutoencoderUploadManifest { latent_shape: vec![1 << 20, 1 << 20], ..m.to_proto() },
                "h.latent_shape: [1048576, 1048576] has more than",
            ),
            (pb::AutoencoderUploadManifest { scaling_factor: Some(0.0), ..m.to_proto() }, "h.scaling_factor: 0"),
            (pb::AutoencoderUploadManifest { scaling_factor: Some(f64::NAN), ..m.to_proto() }, "h.scaling_factor: NaN"),
            (pb::AutoencoderUploadManifest { shift_factor: Some(f64::INFINITY), ..m.to_proto() }, "h.shift_factor"),
        ];
        for (wire, needle) in cases {
            let err = AutoencoderManifest::from_proto(wire, "h").expect_err(needle);
            assert!(err.0.starts_with(needle), "{} should start with {needle}", err.0);
        }
        let err = AutoencoderManifest::parse("image_shape = [1]\nlatent_shape = [1]\nscale = 2\n", None)
            .expect_err("unknown field");
        assert!(err.0.contains("unknown field `scale`"), "{}", err.0);
    }
}
