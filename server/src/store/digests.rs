//! Per-blob digest lists: every published file set carries the sha256 of each of its files.
//!
//! A [`BlobStore`](super::BlobStore) writes [`DIGEST_FILE`] into the staging directory just
//! before publishing it (so the list is published atomically with the files it describes),
//! in `sha256sum` format: `<hex>  <file name>` per line, sorted by name, so an operator can
//! check a blob with `sha256sum -c SHA256SUMS`. Readers call [`verify_dir`] once per load
//! (a job loading a dataset, the registry loading a model, a job resuming a checkpoint), never
//! per request.
//!
//! Blobs published before digest lists existed have none; [`verify_dir`] reports that as
//! [`Verified::NoList`] and the caller falls back to the digest in the resource's record (a
//! model's file sha256, a dataset's payload sha256) where there is one.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use sha2::{Digest, Sha256};

use crate::error::{Error, Result};

/// The digest list's file name inside a blob.
pub const DIGEST_FILE: &str = "SHA256SUMS";

/// Lowercase hex sha256 and size of a file, read in 1 MiB blocks.
pub fn sha256_file(path: &Path) -> std::io::Result<(String, u64)> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut size = 0u64;
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    Ok((hex::encode(hasher.finalize()), size))
}

/// Hashes every regular file of `dir` (blobs are flat) and writes the list (blocking).
pub fn write_list(dir: &Path) -> Result<()> {
    let mut sums = BTreeMap::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name == DIGEST_FILE || !entry.file_type()?.is_file() {
            continue;
        }
        sums.insert(name, sha256_file(&entry.path())?.0);
    }
    let text: String = sums.iter().map(|(name, sum)| format!("{sum}  {name}\n")).collect();
    std::fs::write(dir.join(DIGEST_FILE), text)?;
    Ok(())
}

/// What [`verify_dir`] found.
#[derive(Debug, PartialEq, Eq)]
pub enum Verified {
    /// Every listed file is present and matches; the map holds each file's sha256.
    Intact(BTreeMap<String, String>),
    /// The blob predates digest lists.
    NoList,
}

/// Checks every file listed in `dir`'s digest list (blocking). A mismatch, a missing file or
/// an unreadable list is `DataLoss` naming `what` (e.g. "model 'base'") and the file.
pub fn verify_dir(dir: &Path, what: &str) -> Result<Verified> {
    let text = match std::fs::read(dir.join(DIGEST_FILE)) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if !dir.is_dir() {
                return Err(Error::DataLoss(format!("{what}: its stored files are missing")));
            }
            return Ok(Verified::NoList);
        }
        Err(e) => return Err(e.into()),
    };
    let corrupt = |detail: String| Error::DataLoss(format!("{what} is corrupt: {detail}"));
    let text = String::from_utf8(text).map_err(|_| corrupt(format!("{DIGEST_FILE} is not text")))?;
    let mut sums = BTreeMap::new();
    for line in text.lines() {
        let (sum, name) = line
            .split_once("  ")
            .filter(|(sum, name)| {
                sum.len() == 64
                    && sum.bytes().all(|b| b.is_ascii_hexdigit())
                    && !name.is_empty()
                    && !name.contains(['/', '\\'])
                    && *name != ".."
            })
            .ok_or_else(|| corrupt(format!("{DIGEST_FILE} has a malformed line")))?;
        let actual = match sha256_file(&dir.join(name)) {
            Ok((actual, _)) => actual,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(corrupt(format!("stored file {name} is missing")));
            }
            Err(e) => return Err(e.into()),
        };
        if actual != sum {
            return Err(corrupt(format!(
                "stored file {name} fails its integrity check (sha256 {actual}, recorded {sum})"
            )));
        }
        sums.insert(name.to_owned(), actual);
    }
    Ok(Verified::Intact(sums))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_verify_and_detect_flipped_bytes_missing_files_and_bad_lists() {
        let tmp = tempfile::tempdir().expect("tmp");
        let dir = tmp.path();
        assert_eq!(verify_dir(dir, "x").expect("no list"), Verified::NoList);
        std::fs::write(dir.join("a.npy"), b"hello").expect("a");
        std::fs::write(dir.join("b.json"), b"{}").expect("b");
        write_list(dir).expect("list");
        let Verified::Intact(sums) = verify_dir(dir, "x").expect("intact") else { panic!("no list") };
        assert_eq!(sums.len(), 2);
        assert_eq!(sums["a.npy"], "2cf24dba5fb0a30e26e83b2ac5b9e29e1b161e5c1fa7425e73043362938b9824");

        std::fs::write(dir.join("a.npy"), b"hellp").expect("flip");
        match verify_dir(dir, "dataset 'd'") {
            Err(Error::DataLoss(m)) => assert!(m.contains("dataset 'd' is corrupt") && m.contains("a.npy"), "{m}"),
            other => panic!("expected DataLoss, got {other:?}"),
        }
        std::fs::write(dir.join("a.npy"), b"hello").expect("restore");
        std::fs::remove_file(dir.join("b.json")).expect("rm");
        assert!(matches!(verify_dir(dir, "x"), Err(Error::DataLoss(m)) if m.contains("b.json is missing")));
        std::fs::write(dir.join(DIGEST_FILE), "zz  a.npy\n").expect("bad list");
        assert!(matches!(verify_dir(dir, "x"), Err(Error::DataLoss(m)) if m.contains("malformed")));
        assert!(matches!(verify_dir(&dir.join("gone"), "x"), Err(Error::DataLoss(m)) if m.contains("missing")));
    }
}
