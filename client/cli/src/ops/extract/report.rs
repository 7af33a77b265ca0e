//! `report.md` and `report.json`: what [`super::pipeline`] made, written into the run's
//! directory (by `extract`, and by `demo` beside its own summary).

use anyhow::Result;
use serde_json::{Value, json};

use super::{Extracted, Inputs, path_str};
use crate::train::flags::AlgorithmArg;

/// The report of a run, as written.
#[derive(Debug, Clone)]
pub struct RunReport {
    pub markdown: String,
    pub json: Value,
}

/// Writes `report.md` and `report.json` into `inputs.out` and returns them. `demo_layout`
/// marks a demo's run (`"demo": {"layout": ..}` in the JSON).
pub fn write_report(inputs: &Inputs, e: &Extracted, elapsed: f64, demo_layout: Option<&str>) -> Result<RunReport> {
    let with_goal: Vec<bool> = e.experts.iter().filter_map(|r| r.goal_recovered()).collect();
    let at_rest: Vec<bool> = e.experts.iter().filter_map(|r| r.goal_recovered_at_rest()).collect();
    let mut report = json!({
        "base_data": path_str(&inputs.base),
        "algorithm": algorithm_number(inputs.algorithm),
        "seed": inputs.seed,
        "profiles": e.profiles.iter().map(|p| json!({
            "rows": p.rows, "episodes": p.episodes, "episode_len_min_q25_median_max": p.episode_len,
            "displacement_per_row": p.displacement_per_row,
        })).collect::<Vec<_>>(),
        "sizes": e.sizes,
        "models": {"base": e.base_model, "experts": e.expert_models, "rewards": e.rewards},
        "rewards": e.experts,
        "goals_recovered": with_goal.iter().filter(|&&r| r).count(),
        "goals_evaluated": with_goal.len(),
        "goals_recovered_at_rest": at_rest.iter().filter(|&&r| r).count(),
        "goals_evaluated_at_rest": at_rest.len(),
        "mean_balanced_accuracy": mean_balanced_accuracy(e),
        "elapsed_seconds": elapsed,
        "out": path_str(&inputs.out),
    });
    if let (Some(layout), Value::Object(r)) = (demo_layout, &mut report) {
        r.insert("demo".to_owned(), json!({ "layout": layout }));
    }
    let markdown = markdown(inputs, e, elapsed, &with_goal, &at_rest)?;
    std::fs::write(inputs.out.join("report.md"), &markdown)?;
    std::fs::write(inputs.out.join("report.json"), serde_json::to_string_pretty(&report)?)?;
    Ok(RunReport { markdown, json: report })
}

/// 1 or 2.
fn algorithm_number(algorithm: AlgorithmArg) -> u8 {
    match algorithm {
        AlgorithmArg::WithDataset => 1,
        AlgorithmArg::ModelsOnly => 2,
    }
}

/// The mean held-out balanced accuracy of the rewards (those that are numbers).
pub fn mean_balanced_accuracy(e: &Extracted) -> f64 {
    let accuracies: Vec<f64> = e.experts.iter().map(|r| r.reward.balanced_accuracy).filter(|a| a.is_finite()).collect();
    accuracies.iter().sum::<f64>() / accuracies.len().max(1) as f64
}

fn markdown(inputs: &Inputs, e: &Extracted, elapsed: f64, with_goal: &[bool], at_rest: &[bool]) -> Result<String> {
    let num = |v: f64| if v.is_finite() { format!("{v:.3}") } else { "-".to_owned() };
    let cell = |c: Option<(i64, i64)>| c.map_or("-".to_owned(), |(i, j)| format!("{i},{j}"));
    let yes_no = |v: Option<bool>| match v {
        Some(true) => "yes",
        Some(false) => "no",
        None => "-",
    };
    let mut t = format!(
        "# relreward extract\n\nbase data: `{}`; Algorithm {}; seed {}; {:.0} s\n\nsizes: `{}`\n\n",
        path_str(&inputs.base),
        algorithm_number(inputs.algorithm),
        inputs.seed,
        elapsed,
        serde_json::to_value(&e.sizes)?
    );
    t.push_str("| expert | reward | balanced accuracy | AUC | reward max at | recovered | max at rest | recovered at rest | discriminator accuracy |\n|---|---|---|---|---|---|---|---|---|\n");
    for row in &e.experts {
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            row.label,
            row.reward.model,
            num(row.reward.balanced_accuracy),
            num(row.reward.auc),
            cell(row.argmax_cell()),
            yes_no(row.goal_recovered()),
            cell(row.argmax_cell_at_rest()),
            yes_no(row.goal_recovered_at_rest()),
            row.discriminator.as_ref().map_or("-".to_owned(), |d| num(d.balanced_accuracy)),
        ));
    }
    t.push_str(&format!(
        "\nmean balanced accuracy {}; goals recovered {} of {} evaluated (the paper's heatmap: base sub-trajectories); at rest {} of {}\n\nPictures: `hist-*.png` (reward histograms, base vs expert), `loss-*.png` (loss curves), `heatmap-*.png` (maze reward heatmaps over base sub-trajectories), `heatmap-at-rest-*.png` (the reward of a window held still at each position).\n",
        num(mean_balanced_accuracy(e)),
        with_goal.iter().filter(|&&r| r).count(),
        with_goal.len(),
        at_rest.iter().filter(|&&r| r).count(),
        at_rest.len()
    ));
    Ok(t)
}
