//! The toolkit's file readers (`client/toolkit/src/npz/`) on an arbitrary file: sniffing,
//! .npz archive listing, both dataset readers, and reading every array they accept (streamed
//! and whole).
#![no_main]

use std::io::Read;

use libfuzzer_sys::fuzz_target;
use relreward_toolkit::npz;
use relreward_client::upload::UploadSource;

fuzz_target!(|data: &[u8]| {
    let mut file = tempfile::NamedTempFile::new().expect("temp file");
    std::io::Write::write_all(&mut file, data).expect("write temp file");
    let path = file.path();
    let _ = npz::detect_kind(path);
    let _ = npz::npz_keys(path);
    let sources = [npz::samples_from_npz_or_npy(path, None), npz::trajectories_from_npz(path)];
    for mut source in sources.into_iter().flatten() {
        let _ = source.total_bytes();
        for i in 0..source.arrays().len() {
            let declared = source.arrays()[i].clone();
            if let Ok(mut reader) = source.open(i) {
                let mut sink = Vec::new();
                // A reader never yields more than the file holds.
                if reader.read_to_end(&mut sink).is_ok() {
                    assert!(sink.len() <= data.len(), "{declared:?}");
                }
            }
            let _ = source.read_tensor(i);
        }
    }
});
