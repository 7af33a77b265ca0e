//! Steering (the demo's own measurement): guided sampling from the base model with a reward
//! should put more final states near the goal than unguided sampling. Omega is chosen by a
//! small sweep on one seed and reported on another, so the reported fraction is not the one it
//! was selected on.

use anyhow::{Context, Result};
use relreward_client::{Client, pb};
use serde::Serialize;
use tokio_stream::StreamExt;

/// Final states within this distance (Euclidean, cell units) of the goal count as near it.
pub const NEAR_GOAL: f64 = 1.0;

/// One omega of the sweep and the fraction of final states it put near the goal.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SweepPoint {
    pub omega: f64,
    pub near_goal: f64,
}

/// Unguided vs guided sampling with the omega the sweep chose.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Steering {
    pub omega: f64,
    pub sweep: Vec<SweepPoint>,
    pub samples: u32,
    pub near_goal_radius_cells: f64,
    pub unguided_near_goal: f64,
    pub guided_near_goal: f64,
}

impl Steering {
    /// Whether guidance put more final states near the goal.
    pub fn steered(&self) -> bool {
        self.guided_near_goal > self.unguided_near_goal
    }
}

/// Fraction of `n` sampled trajectories whose last state lies near `goal` (rows
/// `[action (2) | x, y, vx, vy]`); `omega == 0` samples unguided.
async fn near_goal_fraction(
    client: &Client,
    base: &str,
    reward: &str,
    omega: f64,
    goal: (usize, usize),
    n: u32,
    seed: u64,
) -> Result<f64> {
    let request = pb::SampleRequest {
        model: base.into(),
        reward_model: if omega == 0.0 { String::new() } else { reward.into() },
        omega,
        n,
        seed: Some(seed),
        ..Default::default()
    };
    let mut stream = client.sample(request).await?;
    let (mut near, mut count) = (0usize, 0usize);
    while let Some(item) = stream.next().await {
        let item = item?;
        let x = item.x.as_ref().context("a sample without x")?;
        let values = relreward_client::tensor::decode_finite_f32(x)?;
        let d = *x.shape.last().context("a scalar sample")? as usize;
        // Rows are [action (2) | x, y, vx, vy]: the last row's position.
        let last = &values[values.len() - d..];
        let (px, py) = (f64::from(last[2]), f64::from(last[3]));
        if (px - goal.0 as f64).hypot(py - goal.1 as f64) <= NEAR_GOAL {
            near += 1;
        }
        count += 1;
    }
    Ok(near as f64 / count.max(1) as f64)
}

/// Steering of `reward` on `base` toward the goal cell: the sweep over `omegas` with
/// `samples / 2 + 1` samples on seed + 1000, then unguided and guided with the best omega,
/// `samples` each, on seed + 2000.
pub async fn steer(
    client: &Client,
    base: &str,
    reward: &str,
    goal: (usize, usize),
    omegas: &[f64],
    samples: u32,
    seed: u64,
) -> Result<Steering> {
    let (sweep_seed, report_seed) = (seed.wrapping_add(1000), seed.wrapping_add(2000));
    let mut sweep = Vec::new();
    for &omega in omegas {
        let near_goal = near_goal_fraction(client, base, reward, omega, goal, samples / 2 + 1, sweep_seed).await?;
        sweep.push(SweepPoint { omega, near_goal });
    }
    let best = sweep.iter().copied().max_by(|a, b| a.near_goal.total_cmp(&b.near_goal)).map_or(0.0, |p| p.omega);
    let unguided = near_goal_fraction(client, base, reward, 0.0, goal, samples, report_seed).await?;
    let guided = near_goal_fraction(client, base, reward, best, goal, samples, report_seed).await?;
    Ok(Steering {
        omega: best,
        sweep,
        samples,
        near_goal_radius_cells: NEAR_GOAL,
        unguided_near_goal: unguided,
        guided_near_goal: guided,
    })
}
