//! Model manifests (`server/src/engine/manifest.rs`): TOML or JSON text, parsed and validated,
//! then the derived quantities the engine computes from an accepted manifest.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_server::engine::manifest::DiffusionManifest;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(m) = DiffusionManifest::parse(text) {
        let _ = m.space.item_shape();
        let _ = m.space.coordinates();
        let _ = m.space.normalizer_dims();
        // An accepted manifest survives its own JSON form (how it is stored).
        let json = serde_json::to_string(&m).expect("serializes");
        DiffusionManifest::parse(&json).expect("stored form parses again");
    }
});
