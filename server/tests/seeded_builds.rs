//! The same seed gives the same first weights whatever the rest of the server builds at that
//! moment. Layers draw their first values from libtorch's process-wide generator: a training job
//! seeds it and builds its network while other jobs start and while loads (registry, sampling)
//! and serving helpers (replicas) build networks on other threads. A binary of its own, with one
//! test: the library's unit tests draw inputs from that generator without any lock, and a second
//! test here would reseed it under the first.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use relreward_server::engine::manifest::{Architecture, Space};
use relreward_server::engine::nets::{NativeDenoiser, RewardArchitecture, RewardNet};
use tch::{Device, Kind, Tensor};

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

/// The generator's next draws (which a build that drew nothing leaves as they were).
fn next_draws() -> Vec<f32> {
    Vec::<f32>::try_from(Tensor::rand([16], (Kind::Float, Device::Cpu))).expect("float32 draws")
}

#[test]
fn seeded_builds_draw_the_same_weights_beside_other_builds_and_loads_draw_nothing() {
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

    // A load and a replica take no draws: the generator's stream goes on as if they had not run
    // (and what they hold is the file's and the source's values, checked elsewhere).
    tch::manual_seed(5);
    let want = next_draws();
    tch::manual_seed(5);
    let loaded = RewardNet::load(&reward_arch, &[16, 6], &reward_path, Device::Cpu).expect("loads");
    loaded.replica().expect("a replica");
    NativeDenoiser::load(&denoiser_arch, &space, &denoiser_path, None, Device::Cpu).expect("loads");
    assert_eq!(next_draws(), want, "a load or a replica drew from libtorch's generator");
    assert_eq!(
        values(loaded.weights().var_store().variables()),
        values(reward.weights().var_store().variables()),
        "the load holds the file's values"
    );

    // Seeded builds of two seeds on two threads at once, loads and replicas on a third: every
    // build equals its seed's first. They go on until both seeds have been built this many
    // times beside the other (a lock need not be fair: a count on one thread alone could test
    // no contention at all).
    const BUILDS: usize = 50;
    let first = [seeded(11), seeded(12)];
    assert_ne!(first[0], first[1], "another seed, other weights");
    let counts = Arc::new([AtomicUsize::new(0), AtomicUsize::new(0)]);
    let done = |counts: &[AtomicUsize; 2]| counts.iter().all(|c| c.load(Ordering::Relaxed) >= BUILDS);
    let deadline = Instant::now() + Duration::from_secs(60);
    let builders: Vec<_> = (0..2)
        .map(|i| {
            let (counts, want) = (counts.clone(), first[i].clone());
            std::thread::spawn(move || {
                let mut mismatches = 0usize;
                while !done(&counts) && Instant::now() < deadline {
                    mismatches += usize::from(seeded(11 + i as u64) != want);
                    counts[i].fetch_add(1, Ordering::Relaxed);
                }
                mismatches
            })
        })
        .collect();
    let loader = {
        let counts = counts.clone();
        std::thread::spawn(move || {
            while !done(&counts) && Instant::now() < deadline {
                let net = RewardNet::load(&reward_arch, &[16, 6], &reward_path, Device::Cpu).expect("loads");
                net.replica().expect("a replica");
                NativeDenoiser::load(&denoiser_arch, &space, &denoiser_path, None, Device::Cpu).expect("loads");
            }
        })
    };
    let mismatches: Vec<usize> = builders.into_iter().map(|h| h.join().expect("a builder thread")).collect();
    loader.join().expect("the loader thread");
    assert!(done(&counts), "the builds did not finish in time: {counts:?}");
    assert_eq!(mismatches, [0, 0], "seeded builds that drew other weights, per seed, of {BUILDS} or more each");
}
