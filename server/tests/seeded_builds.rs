//! The same seed gives the same first weights whatever the rest of the server builds at that
//! moment. Layers draw their first values from libtorch's process-wide generator; a training job
//! seeds it and builds its network while loads (registry, sampling) and serving helpers
//! (replicas) build networks on other threads. A binary of its own: the library's unit tests
//! draw inputs from that generator without any lock, which this test would see.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use relreward_server::engine::manifest::{Architecture, Space};
use relreward_server::engine::nets::{NativeDenoiser, RewardArchitecture, RewardNet};
use tch::{Device, Tensor};

/// Every variable of a network, in name order, flattened into one vector.
fn values(vars: std::collections::HashMap<String, Tensor>) -> Vec<f32> {
    let mut vars: Vec<(String, Tensor)> = vars.into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars.iter().flat_map(|(_, t)| Vec::<f32>::try_from(t.detach().flatten(0, -1)).expect("float32 weights")).collect()
}

fn seeded(seed: u64) -> Vec<f32> {
    let arch = RewardArchitecture::WindowedMlp { window: 4, hidden: vec![64, 32] };
    values(RewardNet::new(&arch, &[16, 6], seed, Device::Cpu).expect("builds").weights().var_store().variables())
}

#[test]
fn a_seeded_build_draws_the_same_weights_while_other_threads_load_networks() {
    let dir = tempfile::tempdir().expect("tmp");
    let reward_arch = RewardArchitecture::ValueFunction { widths: vec![16, 32] };
    let reward_path = dir.path().join("reward.safetensors");
    let reward = RewardNet::new(&reward_arch, &[16, 6], 1, Device::Cpu).expect("reward builds");
    reward.save(&reward_path).expect("saves");
    let denoiser_arch = Architecture::Mlp { hidden: vec![64, 64] };
    let space = Space::Sample { shape: vec![8] };
    let denoiser_path = dir.path().join("denoiser.safetensors");
    NativeDenoiser::new(&denoiser_arch, &space, None, 2, Device::Cpu)
        .expect("denoiser builds")
        .save(&denoiser_path)
        .expect("saves");

    let first = seeded(11);
    assert_ne!(first, seeded(12), "another seed, other weights");
    // The seeded builds go on until the other threads have built this many networks (a lock
    // need not be fair: counting the seeded builds alone could test no contention at all).
    const LOADS: usize = 100;
    let loads = Arc::new(AtomicUsize::new(0));
    let loaders: Vec<_> = (0..2)
        .map(|i| {
            let (loads, reward_arch, reward_path) = (loads.clone(), reward_arch.clone(), reward_path.clone());
            let (denoiser_arch, space, denoiser_path) = (denoiser_arch.clone(), space.clone(), denoiser_path.clone());
            std::thread::spawn(move || {
                while loads.load(Ordering::Relaxed) < LOADS {
                    let net = RewardNet::load(&reward_arch, &[16, 6], &reward_path, Device::Cpu).expect("loads");
                    if i == 0 {
                        net.replica().expect("a replica");
                    } else {
                        NativeDenoiser::load(&denoiser_arch, &space, &denoiser_path, None, Device::Cpu).expect("loads");
                    }
                    loads.fetch_add(2, Ordering::Relaxed);
                }
            })
        })
        .collect();
    let deadline = Instant::now() + Duration::from_secs(60);
    let (mut builds, mut mismatches) = (0usize, 0usize);
    while loads.load(Ordering::Relaxed) < LOADS && Instant::now() < deadline {
        builds += 1;
        mismatches += usize::from(seeded(11) != first);
    }
    for loader in loaders {
        loader.join().expect("a loader thread");
    }
    assert!(builds >= 10, "only {builds} seeded builds ran beside the loads: no contention was tested");
    assert_eq!(mismatches, 0, "{mismatches} of {builds} seeded builds drew other weights beside {LOADS} loads");
}
