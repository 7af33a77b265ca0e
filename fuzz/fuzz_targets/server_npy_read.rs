//! The server's stored-array reader (`server/src/store/npy.rs` `read`): an arbitrary file read
//! against an arbitrary record (dtype and shape from the first bytes of the input), as when a
//! stored file or its metadata record is damaged.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_proto::v1::Dtype;
use relreward_server::store::npy;

fuzz_target!(|data: &[u8]| {
    let Some((&head, rest)) = data.split_first() else { return };
    let dtype = Dtype::try_from(i32::from(head & 7)).unwrap_or(Dtype::Unspecified);
    let rank = usize::from(head >> 3) % 5;
    if rest.len() < rank * 8 {
        return;
    }
    let (dims, file) = rest.split_at(rank * 8);
    // Small dimensions mostly (so files can match), any u64 now and then.
    let shape: Vec<u64> = dims
        .chunks_exact(8)
        .map(|c| {
            let v = u64::from_le_bytes(c.try_into().expect("8 bytes"));
            if v >> 63 == 1 { v } else { v % 17 }
        })
        .collect();
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("a.npy");
    std::fs::write(&path, file).expect("write temp file");
    if let Ok(a) = npy::read(&path, dtype, &shape) {
        let _ = a.to_f32();
        let _ = a.to_flags();
    }
    // The header writer must round-trip through the client's checked parser.
    if shape.iter().all(|&d| d < 1 << 20) && dtype != Dtype::Unspecified {
        let header = npy::header(dtype, &shape);
        let info = relreward_toolkit::npz::read_npy_header(&mut header.as_slice()).expect("own header parses");
        assert_eq!((info.dtype, info.shape), (dtype, shape));
    }
});
