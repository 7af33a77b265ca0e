//! Bearer tokens: how they are made, stored and checked.
//!
//! A token is `rrt_` followed by 64 hex digits: 256 bits from the operating system's random
//! source (the prefix lets secret scanners and people recognise one). The configuration
//! holds only `sha256:SALT:DIGEST`, where DIGEST = SHA-256(SALT || token) with a random
//! 16-byte SALT, both in hex.
//!
//! Why a fast hash and not argon2 or PBKDF2: those slow down guessing *low-entropy* secrets
//! (passwords) from a stolen hash. Guessing a 256-bit random token is infeasible at any hash
//! speed, while a deliberately slow hash would cost every RPC tens of milliseconds of CPU and
//! hand any anonymous caller a cheap way to burn it. The salt keeps equal tokens from having
//! equal hashes across entries and servers.
//!
//! Checking a presented token hashes it with every entry's salt and compares the digests in
//! constant time (`subtle`), visiting every entry whatever matched, so the time taken does
//! not tell how close a guess was or which entry it hit.

use std::fmt;
use std::sync::Arc;
use std::time::SystemTime;

use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;
use time::OffsetDateTime;
use time::format_description::well_known::Rfc3339;

use super::scopes::Scope;
use crate::config::TokenConfig;

pub const TOKEN_PREFIX: &str = "rrt_";
const TOKEN_BYTES: usize = 32;
const SALT_BYTES: usize = 16;
const HASH_SCHEME: &str = "sha256";
/// Longest token name (names appear in logs and in PERMISSION_DENIED messages).
const MAX_NAME_LEN: usize = 64;
/// Presented credentials longer than this are refused without hashing.
const MAX_PRESENTED_LEN: usize = 1024;

/// A configured token that is not usable as written; `key` names the configuration entry.
#[derive(Debug, thiserror::Error)]
#[error("configuration key {key}: {message}")]
pub struct TokenConfigError {
    pub key: String,
    pub message: String,
}

/// Who made a call: the configured name of the token and the highest scope it carries.
/// Inserted into the request's extensions for handlers that want to say who did what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Principal {
    pub name: Arc<str>,
    pub scope: Scope,
}

struct Entry {
    principal: Principal,
    salt: [u8; SALT_BYTES],
    digest: [u8; 32],
    /// Seconds since the Unix epoch after which the token is refused.
    expires: Option<i64>,
}

/// The configured tokens, parsed once at start.
pub struct TokenTable {
    entries: Vec<Entry>,
}

impl fmt::Debug for TokenTable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Names only: salts and digests stay out of logs.
        f.debug_list().entries(self.entries.iter().map(|e| &*e.principal.name)).finish()
    }
}

/// The outcome of checking a presented token.
#[derive(Debug, PartialEq, Eq)]
pub enum Verdict {
    Valid(Principal),
    /// It matches an entry whose `expires` has passed.
    Expired {
        name: Arc<str>,
        expires: String,
    },
    /// It matches no entry.
    Unknown,
}

impl TokenTable {
    /// Parses `security.tokens`; every error names the entry (`security.tokens[i]`) and field.
    pub fn from_config(tokens: &[TokenConfig]) -> Result<Self, TokenConfigError> {
        let mut entries: Vec<Entry> = Vec::with_capacity(tokens.len());
        for (i, t) in tokens.iter().enumerate() {
            let err = |field: &str, message: String| TokenConfigError {
                key: format!("security.tokens[{i}].{field}"),
                message,
            };
            check_name(&t.name).map_err(|m| err("name", m))?;
            if entries.iter().any(|e| *e.principal.name == *t.name) {
                return Err(err("name", format!("'{}' is used by two tokens; names must be unique", t.name)));
            }
            let (salt, digest) = parse_hash(&t.hash).map_err(|m| err("hash", m))?;
            if entries.iter().any(|e| e.salt == salt && e.digest == digest) {
                return Err(err("hash", "is the same as another token's hash".into()));
            }
            if t.scopes.is_empty() {
                return Err(err("scopes", "empty; list at least one of \"read\", \"train\", \"admin\"".into()));
            }
            let mut scope = Scope::Read;
            for s in &t.scopes {
                let parsed = Scope::parse(s).ok_or_else(|| {
                    err("scopes", format!("'{}' is not a scope (\"read\", \"train\" or \"admin\")", s.escape_default()))
                })?;
                scope = scope.max(parsed);
            }
            let expires = match t.expires.as_deref() {
                None | Some("") => None,
                Some(text) => Some(parse_expiry(text).map_err(|m| err("expires", m))?),
            };
            entries.push(Entry { principal: Principal { name: t.name.as_str().into(), scope }, salt, digest, expires });
        }
        Ok(Self { entries })
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Names of tokens whose expiry has passed at `now` (for a warning at start).
    pub fn expired_names(&self, now: SystemTime) -> Vec<&str> {
        let now = unix_seconds(now);
        self.entries.iter().filter(|e| e.expires.is_some_and(|x| now >= x)).map(|e| &*e.principal.name).collect()
    }

    /// Checks `presented` against every entry.
    pub fn verify(&self, presented: &str, now: SystemTime) -> Verdict {
        if presented.len() > MAX_PRESENTED_LEN {
            return Verdict::Unknown;
        }
        let mut found: Option<&Entry> = None;
        for entry in &self.entries {
            let digest = hash_with_salt(&entry.salt, presented);
            // No early exit: every entry costs the same whether or not one matched before.
            if bool::from(digest.ct_eq(&entry.digest)) {
                found = Some(entry);
            }
        }
        let Some(entry) = found else { return Verdict::Unknown };
        match entry.expires {
            Some(expires) if unix_seconds(now) >= expires => {
                Verdict::Expired { name: entry.principal.name.clone(), expires: format_unix(expires) }
            }
            _ => Verdict::Valid(entry.principal.clone()),
        }
    }
}

/// Token names: 1 to 64 of `[A-Za-z0-9._-]` (they go into logs and TOML unquoted-safe).
pub fn check_name(name: &str) -> Result<(), String> {
    let ok = !name.is_empty()
        && name.len() <= MAX_NAME_LEN
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if ok {
        Ok(())
    } else {
        Err(format!("'{}' is not a token name (1 to 64 of [A-Za-z0-9._-])", name.escape_default()))
    }
}

fn hash_with_salt(salt: &[u8], token: &str) -> [u8; 32] {
    let mut h = Sha256::new();
    h.update(salt);
    h.update(token.as_bytes());
    h.finalize().into()
}

/// `sha256:SALT:DIGEST` -> (salt, digest).
fn parse_hash(text: &str) -> Result<([u8; SALT_BYTES], [u8; 32]), String> {
    let expected = "expected sha256:SALT:DIGEST with a 32-digit hex SALT and a 64-digit hex DIGEST, as printed by \
                    `relreward-server token create` (the token itself never goes in the configuration)";
    let mut parts = text.split(':');
    let (Some(scheme), Some(salt), Some(digest), None) = (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        if text.starts_with(TOKEN_PREFIX) {
            return Err(format!("looks like a token, not a hash: {expected}"));
        }
        return Err(expected.into());
    };
    if scheme != HASH_SCHEME {
        return Err(format!("unknown scheme '{}': {expected}", scheme.escape_default()));
    }
    let mut salt_bytes = [0u8; SALT_BYTES];
    let mut digest_bytes = [0u8; 32];
    hex::decode_to_slice(salt, &mut salt_bytes).map_err(|_| format!("bad SALT: {expected}"))?;
    hex::decode_to_slice(digest, &mut digest_bytes).map_err(|_| format!("bad DIGEST: {expected}"))?;
    Ok((salt_bytes, digest_bytes))
}

fn parse_expiry(text: &str) -> Result<i64, String> {
    OffsetDateTime::parse(text, &Rfc3339)
        .map(OffsetDateTime::unix_timestamp)
        .map_err(|e| format!("'{}' is not an RFC 3339 time such as 2027-01-31T00:00:00Z: {e}", text.escape_default()))
}

fn unix_seconds(t: SystemTime) -> i64 {
    match t.duration_since(SystemTime::UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_secs()).unwrap_or(i64::MAX),
        Err(e) => -i64::try_from(e.duration().as_secs()).unwrap_or(i64::MAX),
    }
}

/// RFC 3339 in UTC (for messages and `token create`).
pub fn format_unix(seconds: i64) -> String {
    OffsetDateTime::from_unix_timestamp(seconds)
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| format!("{seconds} s after 1970-01-01T00:00:00Z"))
}

/// A new token and the hash to configure for it.
pub struct NewToken {
    /// Shown once to the operator; never stored by the server.
    pub token: String,
    /// `sha256:SALT:DIGEST`.
    pub hash: String,
}

/// Draws a token and a salt from the operating system's random source.
pub fn generate() -> Result<NewToken, getrandom::Error> {
    let mut secret = [0u8; TOKEN_BYTES];
    let mut salt = [0u8; SALT_BYTES];
    getrandom::fill(&mut secret)?;
    getrandom::fill(&mut salt)?;
    let token = format!("{TOKEN_PREFIX}{}", hex::encode(secret));
    let hash = hash_string(&salt, &token);
    Ok(NewToken { token, hash })
}

fn hash_string(salt: &[u8], token: &str) -> String {
    format!("{HASH_SCHEME}:{}:{}", hex::encode(salt), hex::encode(hash_with_salt(salt, token)))
}

/// `--expires` of `token create`: an RFC 3339 time, or a lifetime from `now` such as `90d`,
/// `12h` or `30m`. Returns the RFC 3339 text to configure.
pub fn expiry_from_arg(arg: &str, now: SystemTime) -> Result<String, String> {
    if let Ok(seconds) = parse_expiry(arg) {
        return Ok(format_unix(seconds));
    }
    let (number, unit) = arg.split_at(arg.len().saturating_sub(1));
    let per_unit: i64 = match unit {
        "d" => 86_400,
        "h" => 3_600,
        "m" => 60,
        _ => {
            return Err(format!(
                "'{arg}' is neither an RFC 3339 time (2027-01-31T00:00:00Z) nor a lifetime (90d, 12h, 30m)"
            ));
        }
    };
    let n: i64 = number.parse().ok().filter(|n| *n > 0).ok_or_else(|| {
        format!(
            "'{arg}': the lifetime must be a positive whole number of {}",
            match unit {
                "d" => "days",
                "h" => "hours",
                _ => "minutes",
            }
        )
    })?;
    let at = n
        .checked_mul(per_unit)
        .and_then(|s| s.checked_add(unix_seconds(now)))
        .ok_or_else(|| format!("'{arg}' is too far in the future"))?;
    if OffsetDateTime::from_unix_timestamp(at).is_err() {
        return Err(format!("'{arg}' is too far in the future"));
    }
    Ok(format_unix(at))
}

/// One TOML inline table for `security.tokens`.
pub fn config_entry(name: &str, hash: &str, scopes: &[Scope], expires: Option<&str>) -> String {
    let scopes = scopes.iter().map(|s| format!("\"{s}\"")).collect::<Vec<_>>().join(", ");
    let expires = expires.map(|e| format!(", expires = \"{e}\"")).unwrap_or_default();
    format!("{{ name = \"{name}\", hash = \"{hash}\", scopes = [{scopes}]{expires} }}")
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn entry(name: &str, hash: &str, scopes: &[&str], expires: Option<&str>) -> TokenConfig {
        TokenConfig {
            name: name.into(),
            hash: hash.into(),
            scopes: scopes.iter().map(|s| (*s).to_owned()).collect(),
            expires: expires.map(str::to_owned),
        }
    }

    fn at(rfc3339: &str) -> SystemTime {
        SystemTime::UNIX_EPOCH
            + Duration::from_secs(u64::try_from(parse_expiry(rfc3339).expect("time")).expect("after 1970"))
    }

    #[test]
    fn generated_tokens_verify_against_their_hash_only() {
        let a = generate().expect("random");
        let b = generate().expect("random");
        assert!(a.token.starts_with(TOKEN_PREFIX) && a.token.len() == TOKEN_PREFIX.len() + 64);
        assert_ne!(a.token, b.token);
        let table = TokenTable::from_config(&[
            entry("a", &a.hash, &["read"], None),
            entry("b", &b.hash, &["train", "read"], None),
        ])
        .expect("table");
        let now = SystemTime::now();
        assert_eq!(table.verify(&a.token, now), Verdict::Valid(Principal { name: "a".into(), scope: Scope::Read }));
        assert_eq!(table.verify(&b.token, now), Verdict::Valid(Principal { name: "b".into(), scope: Scope::Train }));
        // One character off, a prefix, the hash itself, nothing: unknown.
        let mut off = a.token.clone();
        off.replace_range(10..11, if &a.token[10..11] == "0" { "1" } else { "0" });
        for wrong in [off.as_str(), &a.token[..40], a.hash.as_str(), "", &"x".repeat(5000)] {
            assert_eq!(table.verify(wrong, now), Verdict::Unknown, "{wrong}");
        }
    }

    #[test]
    fn the_hash_is_salted_sha256_of_the_token() {
        // Known answer: sha256(salt || token) for a fixed salt, so the format is pinned.
        let salt = [7u8; SALT_BYTES];
        let token = "rrt_example";
        let hash = hash_string(&salt, token);
        let mut h = Sha256::new();
        h.update(salt);
        h.update(token);
        assert_eq!(hash, format!("sha256:{}:{}", "07".repeat(16), hex::encode(h.finalize())));
        let table = TokenTable::from_config(&[entry("k", &hash, &["read"], None)]).expect("table");
        assert!(matches!(table.verify(token, SystemTime::now()), Verdict::Valid(_)));
        // The same token under another salt has another hash.
        assert_ne!(hash_string(&[8u8; SALT_BYTES], token), hash);
    }

    #[test]
    fn expiry_is_enforced_at_the_second() {
        let t = generate().expect("random");
        let table =
            TokenTable::from_config(&[entry("ci", &t.hash, &["admin"], Some("2030-01-01T00:00:00Z"))]).expect("table");
        let before = at("2029-12-31T23:59:59Z");
        let after = at("2030-01-01T00:00:00Z");
        assert_eq!(
            table.verify(&t.token, before),
            Verdict::Valid(Principal { name: "ci".into(), scope: Scope::Admin })
        );
        assert_eq!(
            table.verify(&t.token, after),
            Verdict::Expired { name: "ci".into(), expires: "2030-01-01T00:00:00Z".into() }
        );
        assert_eq!(table.expired_names(before), Vec::<&str>::new());
        assert_eq!(table.expired_names(after), vec!["ci"]);
        // Offsets are honoured: 01:00+01:00 is midnight UTC.
        let table = TokenTable::from_config(&[entry("x", &t.hash, &["read"], Some("2030-01-01T01:00:00+01:00"))])
            .expect("table");
        assert!(matches!(table.verify(&t.token, after), Verdict::Expired { .. }));
    }

    #[test]
    fn the_highest_listed_scope_wins() {
        let t = generate().expect("random");
        for (scopes, want) in
            [(&["read"][..], Scope::Read), (&["read", "train"], Scope::Train), (&["admin", "read"], Scope::Admin)]
        {
            let table = TokenTable::from_config(&[entry("t", &t.hash, scopes, None)]).expect("table");
            match table.verify(&t.token, SystemTime::now()) {
                Verdict::Valid(p) => assert_eq!(p.scope, want, "{scopes:?}"),
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn bad_entries_name_their_key() {
        let good = generate().expect("random").hash;
        let cases: Vec<(Vec<TokenConfig>, &str)> = vec![
            (vec![entry("", &good, &["read"], None)], "security.tokens[0].name"),
            (vec![entry("a b", &good, &["read"], None)], "security.tokens[0].name"),
            (
                vec![entry("a", &good, &["read"], None), entry("a", &generate().expect("r").hash, &["read"], None)],
                "security.tokens[1].name",
            ),
            (vec![entry("a", &good, &["read"], None), entry("b", &good, &["read"], None)], "security.tokens[1].hash"),
            (vec![entry("a", "rrt_0123", &["read"], None)], "security.tokens[0].hash"),
            (vec![entry("a", "md5:00:00", &["read"], None)], "security.tokens[0].hash"),
            (vec![entry("a", "sha256:zz:00", &["read"], None)], "security.tokens[0].hash"),
            (vec![entry("a", &good[..good.len() - 2], &["read"], None)], "security.tokens[0].hash"),
            (vec![entry("a", &good, &[], None)], "security.tokens[0].scopes"),
            (vec![entry("a", &good, &["write"], None)], "security.tokens[0].scopes"),
            (vec![entry("a", &good, &["read"], Some("tomorrow"))], "security.tokens[0].expires"),
            (vec![entry("a", &good, &["read"], Some("2030-01-01"))], "security.tokens[0].expires"),
        ];
        for (tokens, key) in cases {
            let err = TokenTable::from_config(&tokens).expect_err(key);
            assert_eq!(err.key, key, "{err}");
        }
        let err = TokenTable::from_config(&[entry("a", "rrt_0123", &["read"], None)]).expect_err("token as hash");
        assert!(err.message.contains("looks like a token"), "{err}");
    }

    #[test]
    fn expiry_arguments() {
        let now = at("2030-01-01T00:00:00Z");
        assert_eq!(expiry_from_arg("90d", now).expect("days"), "2030-04-01T00:00:00Z");
        assert_eq!(expiry_from_arg("12h", now).expect("hours"), "2030-01-01T12:00:00Z");
        assert_eq!(expiry_from_arg("30m", now).expect("minutes"), "2030-01-01T00:30:00Z");
        assert_eq!(expiry_from_arg("2031-06-01T12:00:00+02:00", now).expect("rfc3339"), "2031-06-01T10:00:00Z");
        for bad in ["", "d", "0d", "-1d", "1w", "1.5d", "soon", "99999999999999d"] {
            assert!(expiry_from_arg(bad, now).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_config_entry_is_toml_that_loads_back() {
        let t = generate().expect("random");
        let line = config_entry("ci-bot", &t.hash, &[Scope::Read, Scope::Train], Some("2030-01-01T00:00:00Z"));
        #[derive(serde::Deserialize)]
        struct Doc {
            tokens: Vec<TokenConfig>,
        }
        let doc: Doc = toml::from_str(&format!("tokens = [{line}]")).expect("toml");
        let table = TokenTable::from_config(&doc.tokens).expect("table");
        assert!(
            matches!(table.verify(&t.token, at("2029-01-01T00:00:00Z")), Verdict::Valid(p) if p.scope == Scope::Train)
        );
    }
}
