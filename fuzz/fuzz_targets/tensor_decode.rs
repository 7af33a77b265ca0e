//! The Tensor wire codec: any bytes a peer sends, decoded as a `relreward.v1.Tensor` and then
//! through every checked decoder (`proto/src/tensor.rs`). Nothing may panic or allocate more
//! than the message carries.
#![no_main]

use libfuzzer_sys::fuzz_target;
use prost::Message;
use relreward_proto::tensor;
use relreward_proto::v1::Tensor;

fuzz_target!(|data: &[u8]| {
    let Ok(t) = Tensor::decode(data) else { return };
    let _ = tensor::numel(&t.shape);
    let ok = tensor::validate(&t);
    if let Ok(dtype) = ok {
        // A valid tensor's byte count is exactly what its shape and dtype declare.
        assert_eq!(tensor::byte_len(&t.shape, dtype), Ok(t.data.len() as u64));
    }
    let mut n = 0u64;
    let visited = tensor::for_each_float(&t, |_| n += 1);
    if visited.is_ok() {
        assert_eq!(Ok(n), tensor::numel(&t.shape));
    }
    let _ = tensor::decode_finite_f32(&t);
    let _ = tensor::decode_flags(&t);
    if let Ok(dtype) = tensor::known_dtype(t.dtype) {
        let _ = tensor::from_raw(&t.shape, dtype, t.data.clone());
    }
});
