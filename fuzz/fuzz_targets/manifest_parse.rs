//! Model manifests (`proto/src/schema/manifest.rs`): TOML or JSON text, parsed and validated,
//! then the derived quantities the engine computes from an accepted manifest.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relreward_proto::schema::manifest::DiffusionManifest;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(m) = DiffusionManifest::parse(text, None) {
        let _ = m.space.item_shape();
        let _ = m.space.coordinates();
        let _ = m.space.normalizer_dims();
        // An accepted manifest survives its own JSON form (how it is stored).
        let json = serde_json::to_string(&m).expect("serializes");
        DiffusionManifest::parse(&json, None).expect("stored form parses again");
        // And its wire form converts back to the same manifest.
        assert_eq!(DiffusionManifest::from_proto(Some(m.to_proto()), "m").as_ref(), Ok(&m));
    }
});
