//! The container: whether a file is one `.npy` array or an `.npz` (a zip of `.npy` members),
//! the archive's members by name, and one member's header or values read with the checks every
//! reader needs (a member holding less data than its header declares is refused at open).
//!
//! Also the readers of single arrays by name that do not make an upload: [`npz_keys`],
//! [`read_numbers`], [`npz_array_shape`].

use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::Path;

use npyz::zip::ZipArchive;

use super::error::{NpzError, Result, invalid_data};
use super::npy::{Header, NPY_MAGIC, read_header, read_values};

/// An open `.npz` archive.
pub(super) type Archive = ZipArchive<BufReader<File>>;

/// What a file starts with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum FileFormat {
    Npy,
    Npz,
}

/// Whether `path` is an `.npy` array or an `.npz` (zip) archive, from its first bytes.
pub(super) fn sniff(path: &Path) -> Result<FileFormat> {
    let mut file = File::open(path).map_err(|e| NpzError::new(path, e.to_string()))?;
    let mut magic = [0u8; 6];
    let mut got = 0;
    while got < magic.len() {
        match file.read(&mut magic[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(NpzError::new(path, e.to_string())),
        }
    }
    if got == magic.len() && &magic == NPY_MAGIC {
        Ok(FileFormat::Npy)
    } else if got >= 4 && (magic[..4] == *b"PK\x03\x04" || magic[..4] == *b"PK\x05\x06") {
        Ok(FileFormat::Npz)
    } else {
        Err(NpzError::new(path, "not an .npy or .npz file"))
    }
}

/// One array of an archive: its name (the entry's file name without `.npy`) and entry index.
#[derive(Debug, Clone)]
pub(super) struct Member {
    pub(super) key: String,
    pub(super) index: usize,
}

/// Opens an `.npz` archive and lists its arrays (entries named `*.npy`), refusing a name held twice.
pub(super) fn open_archive(path: &Path) -> Result<(Archive, Vec<Member>)> {
    let file = File::open(path).map_err(|e| NpzError::new(path, e.to_string()))?;
    let mut archive = ZipArchive::new(BufReader::new(file))
        .map_err(|e| NpzError::new(path, format!("not a readable .npz archive: {e}")))?;
    let mut members: Vec<Member> = Vec::new();
    for index in 0..archive.len() {
        let entry = archive
            .by_index_raw(index)
            .map_err(|e| NpzError::new(path, format!("reading archive entry {index}: {e}")))?;
        if entry.is_dir() {
            continue;
        }
        let Some(key) = npyz::npz::array_name_from_file_name(entry.name()) else {
            continue;
        };
        if members.iter().any(|m| m.key == key) {
            return Err(NpzError::new(path, format!("the archive holds array '{key}' twice")));
        }
        members.push(Member { key: key.to_owned(), index });
    }
    Ok((archive, members))
}

/// Reads the header of archive member `member`, checking that the entry holds all the data it
/// declares.
pub(super) fn member_header(path: &Path, archive: &mut Archive, member: &Member) -> Result<Header> {
    let key = &member.key;
    let mut entry = archive.by_index(member.index).map_err(|e| NpzError::new(path, format!("array '{key}': {e}")))?;
    let size = entry.size();
    let header = read_header(&mut entry).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    check_complete(path, key, &header, size)?;
    Ok(header)
}

/// The header and every value (as f64) of archive member `member`.
pub(super) fn member_values(path: &Path, archive: &mut Archive, member: &Member) -> Result<(Header, Vec<f64>)> {
    let key = &member.key;
    let header = member_header(path, archive, member)?;
    let mut entry = archive.by_index(member.index).map_err(|e| NpzError::new(path, format!("array '{key}': {e}")))?;
    read_header(&mut entry).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    let values = read_values(&mut entry, &header).map_err(|m| NpzError::new(path, format!("array '{key}': {m}")))?;
    Ok((header, values))
}

/// Refuses an array whose `stored` bytes (header included) hold less data than its header declares.
pub(super) fn check_complete(path: &Path, key: &str, header: &Header, stored: u64) -> Result<()> {
    let available = stored.saturating_sub(header.header_len);
    if available < header.data_len {
        return Err(NpzError::new(
            path,
            format!(
                "array '{key}' is truncated: shape {:?} of {} needs {} data bytes but only {available} are stored",
                header.shape, header.element, header.data_len
            ),
        ));
    }
    Ok(())
}

/// The archive's array names for a message: `'a', 'b'`, or `none`.
pub(super) fn list_keys(members: &[Member]) -> String {
    if members.is_empty() {
        "none".to_owned()
    } else {
        members.iter().map(|m| format!("'{}'", m.key)).collect::<Vec<_>>().join(", ")
    }
}

/// Names of the arrays an `.npz` archive holds, in archive order (for an `.npy` file: none).
pub fn npz_keys(path: impl AsRef<Path>) -> Result<Vec<String>> {
    let path = path.as_ref();
    match sniff(path)? {
        FileFormat::Npy => Ok(Vec::new()),
        FileFormat::Npz => Ok(open_archive(path)?.1.into_iter().map(|m| m.key).collect()),
    }
}

/// One numeric array of an `.npz` (or of a plain `.npy`, whatever `key`) as f64 with its
/// shape; `None` when an archive has no such array. Any integer, bool or float dtype in either
/// byte order ([`crate::values::Element`]), in C order whatever the stored order. Errors do not
/// name the file; callers add it.
pub fn read_numbers(path: &Path, key: &str) -> io::Result<Option<(Vec<u64>, Vec<f64>)>> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy")) {
        let mut reader = BufReader::new(File::open(path)?);
        let header = read_header(&mut reader).map_err(|m| invalid_data(format!("'{key}': {m}")))?;
        let values = read_values(&mut reader, &header).map_err(|m| invalid_data(format!("'{key}': {m}")))?;
        return Ok(Some((header.shape, values)));
    }
    let (mut archive, members) = open_archive(path).map_err(|e| invalid_data(e.message))?;
    let Some(member) = members.iter().find(|m| m.key == key) else { return Ok(None) };
    let (header, values) = member_values(path, &mut archive, member).map_err(|e| invalid_data(e.message))?;
    Ok(Some((header.shape, values)))
}

/// The shape of array `key` of an `.npz` archive, from its header; `None` when the archive has
/// no such array.
pub fn npz_array_shape(path: &Path, key: &str) -> io::Result<Option<Vec<u64>>> {
    let mut archive = npyz::npz::NpzArchive::open(path)?;
    Ok(archive.by_name(key)?.map(|npy| npy.shape().to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::test_files::{d4rl_entries, f64_bytes, npy, read_all, scratch, trajectories_error, write_npz};
    use crate::npz::{detect_kind, read_npy_header, samples_from_npz_or_npy, trajectories_from_npz};
    use relreward_client::client::payload_sha256;

    #[test]
    fn truncated_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().expect("tempdir");
        let full = npy("<f4", false, &[4, 2], &[7; 32]);

        // Cut inside the data: refused when the file is opened.
        let path = dir.path().join("short.npy");
        std::fs::write(&path, &full[..full.len() - 5]).expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("truncated") && err.contains("32 data bytes"), "{err}");
        // Cut inside the header.
        for cut in [0, 3, 9, 20, 127] {
            std::fs::write(&path, &full[..cut]).expect("write");
            assert!(samples_from_npz_or_npy(&path, None).is_err(), "cut at {cut}");
        }

        // Truncated after it was opened: reading fails.
        std::fs::write(&path, &full).expect("write");
        let mut source = samples_from_npz_or_npy(&path, None).expect("open");
        std::fs::write(&path, &full[..full.len() - 5]).expect("truncate");
        let err = read_all(&mut source, 0).expect_err("must fail");
        assert_eq!(err.kind(), io::ErrorKind::UnexpectedEof);
        assert!(err.to_string().contains("27 of its 32 data bytes"), "{err}");
        assert!(payload_sha256(&mut source).is_err());

        // A truncated archive.
        let path = dir.path().join("short.npz");
        let (entries, _) = d4rl_entries();
        write_npz(&path, &entries, true);
        let bytes = std::fs::read(&path).expect("read");
        for cut in [0, 10, bytes.len() / 2, bytes.len() - 1] {
            std::fs::write(&path, &bytes[..cut]).expect("write");
            assert!(trajectories_from_npz(&path).is_err(), "cut at {cut}");
            assert!(detect_kind(&path).is_err(), "cut at {cut}");
        }

        // An archive entry whose data is shorter than its header declares.
        let path = dir.path().join("lying.npz");
        let err = trajectories_error(
            &path,
            &[
                ("observations", npy("<f4", false, &[4, 2], &[0; 31])),
                ("actions", npy("<f4", false, &[4, 1], &[0; 16])),
            ],
        );
        assert!(err.contains("'observations' is truncated"), "{err}");
    }

    #[test]
    fn not_npy_or_npz() {
        let (dir, path) = scratch("x.csv");
        std::fs::write(&path, "a,b\n1,2\n").expect("write");
        let err = samples_from_npz_or_npy(&path, None).expect_err("must fail").to_string();
        assert!(err.contains("not an .npy or .npz file") && err.contains("x.csv"), "{err}");
        assert!(trajectories_from_npz(dir.path().join("missing.npz")).is_err());
    }

    /// A cheap stand-in for fuzzing: flip, cut and splice bytes of valid files and check that
    /// every reader returns (Ok or Err) without panicking.
    #[test]
    fn mutated_files_never_panic() {
        let dir = tempfile::tempdir().expect("tempdir");
        let clean_npz = dir.path().join("clean.npz");
        let (entries, _) = d4rl_entries();
        write_npz(&clean_npz, &entries, false);
        let npz_bytes = std::fs::read(&clean_npz).expect("read");
        let npy_bytes = npy("<f8", false, &[3, 2], &f64_bytes(&[1.0; 6]));
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let path = dir.path().join("mutant");
        for round in 0..600 {
            let base = if round % 2 == 0 { &npz_bytes } else { &npy_bytes };
            let mut bytes = base.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() % bytes.len() as u64) as usize;
                match next() % 4 {
                    0 => bytes[at] ^= 1 << (next() % 8),
                    1 => bytes[at] = b"0123456789(),'<>|fFTx\x00\xff"[(next() % 22) as usize],
                    2 => bytes.truncate(at.max(1)),
                    _ => bytes.insert(at, (next() % 256) as u8),
                }
            }
            std::fs::write(&path, &bytes).expect("write");
            let _ = detect_kind(&path);
            let _ = npz_keys(&path);
            if let Ok(mut s) = trajectories_from_npz(&path) {
                let _ = payload_sha256(&mut s);
            }
            if let Ok(mut s) = samples_from_npz_or_npy(&path, None) {
                let _ = payload_sha256(&mut s);
            }
            let _ = read_npy_header(&mut bytes.as_slice());
        }
    }
}
