//! The checked npy header parser (`read_npy_header` of `client/toolkit/src/npz/npy.rs`) on
//! arbitrary bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_proto::tensor;
use relreward_toolkit::npz;

fuzz_target!(|data: &[u8]| {
    let mut reader = data;
    if let Ok(info) = npz::read_npy_header(&mut reader) {
        // What it accepts is self-consistent: the header was really there and the data size
        // is the one the codec computes.
        assert!(info.header_len <= data.len() as u64);
        assert_eq!(data.len() as u64 - info.header_len, reader.len() as u64);
        assert_eq!(tensor::byte_len(&info.shape, info.dtype), Ok(info.data_len));
    }
});
