//! Job specs (`proto/src/schema/job`): the stored JSON form, deserialized and range-checked by
//! `JobSpec::validate`, and the wire form it goes back out as.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_proto::schema::job::JobSpec;

fuzz_target!(|data: &[u8]| {
    let Ok(spec) = serde_json::from_slice::<JobSpec>(data) else { return };
    let _ = spec.kind.name();
    let _ = spec.inputs();
    let _ = spec.validate();
    let _ = spec.to_proto();
});
