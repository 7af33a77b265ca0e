//! Job specs (`server/src/jobs/spec.rs`): the stored JSON form, deserialized and range-checked
//! by `JobSpec::validate` (the proto -> spec conversion in api/jobs.rs needs a store and is
//! not fuzzed here).
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_server::jobs::spec::JobSpec;

fuzz_target!(|data: &[u8]| {
    let Ok(spec) = serde_json::from_slice::<JobSpec>(data) else { return };
    let _ = spec.kind.name();
    let _ = spec.inputs();
    let _ = spec.validate();
});
