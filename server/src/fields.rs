//! One rule per kind of request field, applied at the door of every RPC that has one, so that
//! the same mistake gets the same answer (INVALID_ARGUMENT naming the field) wherever it is made:
//!
//! - names of datasets, models and jobs ([`validate_name`]): `[a-z0-9][a-z0-9._-]{0,63}`,
//!   checked before any lookup, so a malformed name is never NOT_FOUND;
//! - enums ([`known`]): a value the proto does not define is refused, never read as a default;
//! - page tokens ([`name_page_token`], [`position_page_token`]): only what a List call
//!   returned (or empty) is accepted;
//! - diffusion times ([`diffusion_time`]): t in [0, T) of the model in question;
//! - guidance scales ([`check_omega`]): finite, |omega| <= [`MAX_OMEGA`];
//! - descriptions of datasets, models and recipes ([`check_description`]): at most
//!   [`MAX_DESCRIPTION_BYTES`], since every List call returns them.
//!
//! Messages quote what the client sent with [`crate::error::quote`]: an escaped prefix, and
//! print a client's floating-point number with [`number`]: compact at any magnitude (1e308
//! as `1e308`, not 309 digits).
//!
//! Names are never used as file paths (files live under generated keys), but the name rule
//! still excludes '/', '\\' and a leading '.', so no name can ever be read as a path component.

use crate::error::{Error, Result, quote};

pub const MAX_NAME_LEN: usize = 64;

/// Largest |omega| accepted (Gradient and guided Sample): guidance scales in practice are
/// 1e-3 to 1e2; beyond this a float32 gradient overflows to infinity.
pub const MAX_OMEGA: f64 = 1e6;

/// Checks `name` against the naming rule; `field` is what the message calls it.
pub fn validate_name(field: &str, name: &str) -> Result<()> {
    let mut chars = name.chars();
    let ok_first = chars.next().is_some_and(|c| c.is_ascii_lowercase() || c.is_ascii_digit());
    let ok_rest = chars.all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || matches!(c, '.' | '_' | '-'));
    if ok_first && ok_rest && name.len() <= MAX_NAME_LEN {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "{field}: {} is not a valid name (1 to 64 characters, [a-z0-9] then [a-z0-9._-])",
            quote(name)
        )))
    }
}

/// Largest description a dataset, model or recipe may carry: List calls return descriptions,
/// so a page of unbounded ones could pass the response size limit for every caller.
pub const MAX_DESCRIPTION_BYTES: usize = 4096;

/// A description of at most [`MAX_DESCRIPTION_BYTES`].
pub fn check_description(field: &str, description: &str) -> Result<()> {
    if description.len() > MAX_DESCRIPTION_BYTES {
        return Err(Error::invalid(format!("{field}: {} bytes, at most {MAX_DESCRIPTION_BYTES}", description.len())));
    }
    Ok(())
}

/// Each of `names` (a repeated name field) against the naming rule, as `field[i]`.
pub fn validate_names(field: &str, names: &[String]) -> Result<()> {
    names.iter().enumerate().try_for_each(|(i, n)| validate_name(&format!("{field}[{i}]"), n))
}

/// A proto enum field's value as `E`; a number the proto does not define is refused, with
/// the accepted values (`expected`) in the message.
pub fn known<E: TryFrom<i32>>(field: &str, raw: i32, expected: &str) -> Result<E> {
    E::try_from(raw).map_err(|_| Error::invalid(format!("{field}: unknown value {raw}; expected {expected}")))
}

/// Prefix of the page tokens of listings in name order: a bare name (what a token would be
/// without it) is refused, so only a token a List call handed out is taken back.
const NAME_TOKEN_PREFIX: &str = "after:";

/// The page token of a listing in name order: empty (the first page) or what
/// [`next_name_token`] made of the last name of the previous page; `list` names the call it
/// must come from. Returns the name to list after ("" for the first page).
pub fn name_page_token<'a>(token: &'a str, list: &str) -> Result<&'a str> {
    if token.is_empty() {
        return Ok(token);
    }
    match token.strip_prefix(NAME_TOKEN_PREFIX) {
        Some(name) if validate_name("page.page_token", name).is_ok() => Ok(name),
        _ => Err(Error::invalid(format!("page.page_token: {} is not a token from {list}", quote(token)))),
    }
}

/// The next page's token of a listing in name order, after `last_name`.
pub fn next_name_token(last_name: &str) -> String {
    format!("{NAME_TOKEN_PREFIX}{last_name}")
}

/// The page token of a listing by position: empty (0, the first page) or a non-negative
/// position as a previous page returned it.
pub fn position_page_token(token: &str, list: &str) -> Result<i64> {
    if token.is_empty() {
        return Ok(0);
    }
    match token.parse::<i64>() {
        Ok(p) if p >= 0 && !token.starts_with('+') => Ok(p),
        _ => Err(Error::invalid(format!("page.page_token: {} is not a token from {list}", quote(token)))),
    }
}

/// A diffusion time `t` of a model with `big_t` steps: in [0, T).
pub fn diffusion_time(field: &str, t: i64, big_t: usize) -> Result<()> {
    if (0..big_t as i64).contains(&t) {
        Ok(())
    } else {
        Err(Error::invalid(format!("{field}: {t} is outside [0, {big_t}) for this model (T = {big_t})")))
    }
}

/// `v` as a message shows a number a client sent (the rule both ends share).
pub use relreward_proto::given_number as number;

/// `omega` finite and within [`MAX_OMEGA`]: the rule for a guidance scale.
pub fn check_omega(omega: f64) -> Result<()> {
    if !omega.is_finite() || omega.abs() > MAX_OMEGA {
        return Err(Error::invalid(format!(
            "omega: {} is outside the accepted range [-{MAX_OMEGA:e}, {MAX_OMEGA:e}]",
            number(omega)
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_accept_the_documented_alphabet() {
        for n in ["a", "0", "maze2d-umaze.v1", "x_y", &"a".repeat(64)] {
            assert!(validate_name("name", n).is_ok(), "{n}");
        }
    }

    #[test]
    fn names_reject_everything_else_with_a_short_quote() {
        for n in ["", "A", "-a", ".a", "_a", "a/b", "../x", "a b", "é", "a\0", &"a".repeat(65), &"Z".repeat(1 << 20)] {
            let err = validate_name("header.name", n).expect_err(n).to_string();
            assert!(err.starts_with("header.name:"), "{err}");
            assert!(err.len() < 200, "{} bytes", err.len());
        }
        assert!(validate_names("d", &["ok".into(), "Bad".into()]).unwrap_err().to_string().starts_with("d[1]:"));
    }

    #[test]
    fn enums_page_tokens_times_and_omega() {
        let e = known::<relreward_proto::v1::Units>("input_units", 99, "UNITS_RAW or UNITS_NORMALIZED").unwrap_err();
        assert!(e.to_string().starts_with("input_units: unknown value 99"), "{e}");
        assert_eq!(name_page_token("", "ListModels").expect("empty"), "");
        assert_eq!(name_page_token(&next_name_token("m-1"), "ListModels").expect("a token"), "m-1");
        for bare in ["m-1", "after:", "after:Bad"] {
            assert!(name_page_token(bare, "ListModels").is_err(), "{bare}");
        }
        assert!(name_page_token("!!garbage", "ListModels").unwrap_err().to_string().contains("ListModels"));
        assert_eq!(position_page_token("", "ListJobs").expect("empty"), 0);
        assert_eq!(position_page_token("17", "ListJobs").expect("position"), 17);
        for bad in ["-1", "+3", "x", "99999999999999999999"] {
            assert!(position_page_token(bad, "ListJobs").is_err(), "{bad}");
        }
        assert!(diffusion_time("t", 9, 10).is_ok());
        assert!(diffusion_time("t_stopgrad", 1000, 10).unwrap_err().to_string().starts_with("t_stopgrad: 1000"));
        assert!(diffusion_time("t", -1, 10).is_err());
        assert!(check_omega(1e6).is_ok() && check_omega(-3.0).is_ok());
        for bad in [1e308, f64::NAN, f64::INFINITY, -2e6] {
            assert!(check_omega(bad).unwrap_err().to_string().starts_with("omega:"), "{bad}");
        }
        // The number as sent, compactly: not 309 digits.
        let e = check_omega(1e308).unwrap_err().to_string();
        assert!(e.starts_with("omega: 1e308 is outside") && e.len() < 100, "{e}");
        assert!(check_omega(-1.5e300).unwrap_err().to_string().starts_with("omega: -1.5e300 is"));
    }

    #[test]
    fn numbers_are_shown_compactly_at_any_magnitude() {
        for (v, shown) in [
            (0.0, "0"),
            (0.5, "0.5"),
            (-3.25, "-3.25"),
            (1e-4, "0.0001"),
            (999_999.5, "999999.5"),
            (1e6, "1e6"),
            (1e308, "1e308"),
            (-f64::MAX, "-1.7976931348623157e308"),
            (5e-324, "5e-324"),
            (1.25e-7, "1.25e-7"),
            (f64::NAN, "NaN"),
            (f64::NEG_INFINITY, "-inf"),
        ] {
            assert_eq!(number(v), shown);
        }
    }
}
