"""Turns tests/bench/training.sh's results into the markdown body of BENCHMARKS.md's `training`
section: medians and speed ratios per benchmark, peak RSS, FLOPs per step counted from the
architecture with the arithmetic written out, achieved GFLOP/s and the fraction of this CPU's
fp32 peak.

    report.py RESULTS.jsonl --threads N --sample-n N --command CMD [--wall-seconds S]

RESULTS.jsonl: one {"benchmark", "side", "rep", "result"} per line (training.sh writes them;
the reference's results carry the multiply-accumulates of each network, see bench.py).
"""

import argparse
import datetime
import json
import re
import statistics
import subprocess


def lscpu():
    out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    return {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in out.splitlines() if ":" in line)}


def cpu_peak(threads):
    """(description, GFLOP/s): cores used x GHz x fp32 FLOPs per cycle per core, where FLOPs
    per cycle = 2 FMA pipes x SIMD lanes x 2 (an FMA is a multiply and an add)."""
    info = lscpu()
    flags = info.get("Flags", "").split()
    mhz = float(info.get("CPU max MHz") or 0)
    source = "lscpu max MHz"
    if not mhz:
        with open("/proc/cpuinfo") as f:
            found = re.search(r"cpu MHz\s*:\s*([\d.]+)", f.read())
        mhz, source = (float(found.group(1)), "/proc/cpuinfo cpu MHz (nominal; turbo may be higher)") if found else (0.0, "?")
    if "avx512f" in flags:
        lanes, isa = 16, "AVX-512"
    elif "avx2" in flags and "fma" in flags:
        lanes, isa = 8, "AVX2 + FMA"
    else:
        lanes, isa = 4, "SSE"
    per_cycle = 2 * lanes * 2
    cores = int(info.get("CPU(s)", "1"))
    used = min(threads, cores)
    peak = used * mhz / 1000 * per_cycle
    model = info.get("Model name", "?")
    family = f"family {info.get('CPU family', '?')} model {info.get('Model', '?')}"
    text = (f"{used} core{'s' if used != 1 else ''} x {mhz / 1000:.3f} GHz ({source}) x {per_cycle} FLOP/cycle "
            f"(2 FMA pipes x {lanes} fp32 lanes ({isa}) x 2) = **{peak:.1f} GFLOP/s**")
    machine = (f"{model} ({family}), {cores} CPUs ({info.get('Core(s) per socket', '?')} cores per socket, "
               f"{info.get('Thread(s) per core', '?')} thread per core), {isa}")
    return machine, text, peak


def load(path):
    """(results by (benchmark, side), the 1-minute load averages recorded after each run)."""
    runs, loads = {}, []
    for line in open(path):
        if line.strip():
            r = json.loads(line)
            runs.setdefault((r["benchmark"], r["side"]), []).append(r["result"])
            loads.append(r["load"])
    return runs, loads


def median(values):
    return statistics.median(values)


def fmt_runs(values, digits):
    return ", ".join(f"{v:.{digits}f}" for v in values)


def total(macs):
    return sum(macs.values())


def describe_macs(macs):
    return " + ".join(f"{kind} {v / 1e6:.1f}M" for kind, v in sorted(macs.items())) + f" = {total(macs) / 1e6:.1f}M MACs"


def spread_note(values, limit):
    """min / median / max of one side's runs, and whether max / min exceeds `limit`."""
    lo, mid, hi = min(values), median(values), max(values)
    wide = len(values) > 1 and lo > 0 and hi / lo > limit
    return f"{lo:.2f} / {mid:.2f} / {hi:.2f}", wide


def compiled_section(runs, spread):
    """The torch.compile peer (training.sh, COMPILE=1): its steps/s, compile time and the ratio
    of relreward to it, with each side's spread; a ratio whose sides spread more than `spread`
    (max / min) is marked as not meaningful."""
    out = []
    w = out.append
    rows = [(b, label) for b, label in (("alg1", "Algorithm 1 steps/s"), ("ddpm", "DDPM training steps/s"))
            if (b, "compiled") in runs and (b, "relreward") in runs]
    if not rows:
        return out
    w("")
    w("Against the PyTorch reference under `torch.compile` (inductor, CPU; `bench.py --compile`: Algorithm 1 "
      "compiles the two frozen TemporalUnets, the reward's double backward stays eager since compiled autograd "
      "does not take `create_graph`; DDPM compiles the denoiser's forward and backward), in the same rotation. "
      "Spread = min / median / max steps/s over the runs; a ratio is marked *not meaningful* when either side's "
      f"max / min exceeds {spread:g} (a descheduled run on a shared machine).")
    w("")
    w("| benchmark | relreward (min / median / max) | eager (min / median / max) | compiled (min / median / max) | "
      "compile time s (median) | relreward / eager | relreward / compiled |")
    w("|---|---|---|---|---|---|---|")
    for b, label in rows:
        rr = [r["steps_per_second"] for r in runs[(b, "relreward")]]
        ref = [r["steps_per_second"] for r in runs.get((b, "reference"), [])]
        comp = [r["steps_per_second"] for r in runs[(b, "compiled")]]
        ct = median([r["compile_seconds"] for r in runs[(b, "compiled")] if r.get("compile_seconds") is not None])
        (rr_s, rr_w), (comp_s, comp_w) = spread_note(rr, spread), spread_note(comp, spread)
        ref_s, ref_w = spread_note(ref, spread) if ref else ("n/a", False)

        def ratio(a, b, wide):
            return f"{median(a) / median(b):.2f}x" + (" (*not meaningful: spread*)" if wide else "")

        w(f"| {label} | {rr_s} | {ref_s} | {comp_s} | {ct:.1f} | "
          f"{ratio(rr, ref, rr_w or ref_w) if ref else 'n/a'} | {ratio(rr, comp, rr_w or comp_w)} |")
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--spread", type=float, default=1.25, help="max / min beyond which a ratio is flagged")
    parser.add_argument("results")
    parser.add_argument("--threads", type=int, required=True)
    parser.add_argument("--sample-n", type=int, required=True)
    parser.add_argument("--command", required=True)
    parser.add_argument("--wall-seconds", type=int)
    args = parser.parse_args()
    runs, loads = load(args.results)
    machine, peak_text, peak = cpu_peak(args.threads)
    if not all((b, side) in runs for b in ("alg1", "ddpm", "sample") for side in ("relreward", "reference")):
        # A partial run (training.sh ONLY=...): the comparison tables of what ran, no FLOP section.
        print("## Training against PyTorch (partial run)")
        print("")
        print(f"Machine: {machine}; {args.threads} intra-op thread(s); {datetime.date.today().isoformat()}; "
              f"1-minute load average after each run {min(loads):.1f} to {max(loads):.1f}. Command: `{args.command}`"
              + (f" ({args.wall_seconds} s)." if args.wall_seconds else "."))
        print("\n".join(compiled_section(runs, args.spread)))
        return
    torch_version = runs[("alg1", "reference")][0]["torch"]

    alg1_rr = [r["steps_per_second"] for r in runs[("alg1", "relreward")]]
    alg1_ref = [r["steps_per_second"] for r in runs[("alg1", "reference")]]
    ddpm_rr = [r["steps_per_second"] for r in runs[("ddpm", "relreward")]]
    ddpm_ref = [r["steps_per_second"] for r in runs[("ddpm", "reference")]]
    samp_rr = [1e3 * r["seconds_per_trajectory"] for r in runs[("sample", "relreward")]]
    samp_ref = [1e3 * r["seconds_per_trajectory"] for r in runs[("sample", "reference")]]
    ref_alg1, ref_ddpm, ref_samp = runs[("alg1", "reference")][0], runs[("ddpm", "reference")][0], runs[("sample", "reference")][0]
    alg1_steps, ddpm_steps = ref_alg1["steps"], ref_ddpm["steps"]
    reps = len(alg1_rr)

    # FLOPs per step from the counted MACs (batch 64 in every count).
    unet = total(ref_alg1["macs"]["diffusion"])
    rew = total(ref_alg1["macs"]["reward"])
    unet_ddpm = total(ref_ddpm["macs"]["diffusion"])
    alg1_flops = 2 * (2 * unet) + 6 * (2 * rew)
    ddpm_flops = 3 * (2 * unet_ddpm)
    big_t, n = ref_samp["n_timesteps"], ref_samp["n"]
    unet_s, rew_s = total(ref_samp["macs"]["diffusion"]), total(ref_samp["macs"]["reward"])
    samp_flops = big_t * (2 * unet_s + 2 * (2 * rew_s)) + 2 * rew_s  # per batch of n

    def gflops(flops, per_second):
        return flops * per_second / 1e9

    rows = []
    ratio_alg1 = median(alg1_rr) / median(alg1_ref)
    ratio_ddpm = median(ddpm_rr) / median(ddpm_ref)
    ratio_samp = median(samp_ref) / median(samp_rr)
    out = []
    w = out.append
    w("## Training and sampling against PyTorch")
    w("")
    w("relreward's training jobs and Sample RPC against PyTorch references of the same computations "
      "(`bench/reference/reference.py`: Diffuser's GaussianDiffusion, Trainer and guided `p_sample_loop`, "
      "the paper's Algorithm 1 with `torch.autograd.grad(create_graph=True)`, `torch.optim.Adam`, Diffuser's EMA), "
      "on the same diffusion models and weights (read from relreward's data directory) and the same "
      "libtorch build. `server/tests/training_vs_pytorch.rs` checks that both compute the same numbers "
      "(losses, gradients, weights after Adam and EMA, every denoising step) to 1e-4.")
    w("")
    w(f"Maze configuration scaled to this CPU: horizon 64, D = 6 (observation 4 + action 2), batch 64, "
      f"T = 100 (Diffuser's cosine schedule, x0 parametrization, clip_denoised); diffusion models TemporalUnet "
      f"dim 32, dim_mults (1, 4, 8) ({ref_alg1['parameters']['diffusion'] / 1e6:.2f}M parameters); reward "
      f"windowed MLP h = 4, hidden (128, 64, 32) ({ref_alg1['parameters']['reward'] / 1e3:.1f}k parameters).")
    w("")
    w(f"Machine: {machine}; libtorch {torch_version} (the PyTorch wheel in `.venv`) on both sides with "
      f"{args.threads} intra-op thread{'s' if args.threads != 1 else ''} (relreward `engine.intra_op_threads`, `torch.set_num_threads`); "
      f"{datetime.date.today().isoformat()}. {reps} run{'s' if reps != 1 else ''} per side, alternating relreward and reference; "
      f"medians, all runs in brackets. Command: `{args.command}`"
      + (f" ({args.wall_seconds} s)." if args.wall_seconds else "."))
    cores = int(lscpu().get("CPU(s)", "1"))
    w("")
    busy = max(loads) > cores + 0.5
    w(f"1-minute load average after each run: {min(loads):.1f} to {max(loads):.1f} on {cores} CPUs (the "
      f"benchmark itself accounts for about {args.threads})."
      + (" **Other processes shared the CPUs during this run**, so the figures below are noisy and low on "
         "both sides (with more than one intra-op thread, far lower: libtorch's OpenMP threads wait for each "
         "other at every parallel region, and one descheduled thread stalls the rest); rerun on an idle "
         "machine for figures to quote." if busy else ""))
    w("")
    w("| benchmark | configuration | relreward | PyTorch reference | relreward / reference (speed) |")
    w("|---|---|---|---|---|")
    w(f"| Algorithm 1 steps/s | target mean at x_t, Adam lr 5e-5, EMA; {alg1_steps} steps after a warm-up | "
      f"**{median(alg1_rr):.2f}** ({fmt_runs(alg1_rr, 2)}) | {median(alg1_ref):.2f} ({fmt_runs(alg1_ref, 2)}) | "
      f"**{ratio_alg1:.2f}x** |")
    w(f"| DDPM training steps/s | x0 target, Adam lr 2e-4, EMA; {ddpm_steps} steps after a warm-up | "
      f"**{median(ddpm_rr):.2f}** ({fmt_runs(ddpm_rr, 2)}) | {median(ddpm_ref):.2f} ({fmt_runs(ddpm_ref, 2)}) | "
      f"**{ratio_ddpm:.2f}x** |")
    w(f"| guided sampling, ms per trajectory | {n} trajectories in one batch, T = {big_t}, n_guide_steps 1, "
      f"omega 0.1, t_stopgrad 0, start and goal conditioned; relreward: wall time of `relreward sample` | "
      f"**{median(samp_rr):.1f}** ({fmt_runs(samp_rr, 1)}) | {median(samp_ref):.1f} ({fmt_runs(samp_ref, 1)}) | "
      f"**{ratio_samp:.2f}x** |")
    w("")
    rss = {b: (runs[(b, "relreward-server")][0]["peak_rss_mib"],
               median([r["peak_rss_mib"] for r in runs[(b, "reference")]])) for b in ("alg1", "ddpm", "sample")}
    w("Peak RSS (VmHWM, MiB): relreward's server process (one per benchmark, so it covers that benchmark's "
      "jobs or sampling calls plus the server itself), and the median reference process (Python, torch and "
      "the same work):")
    w("")
    w("| benchmark | relreward server | PyTorch reference |")
    w("|---|---|---|")
    for b, label in (("alg1", "Algorithm 1"), ("ddpm", "DDPM training"), ("sample", "guided sampling")):
        w(f"| {label} | {rss[b][0]:.0f} | {rss[b][1]:.0f} |")
    w("")
    w("FLOPs, counted from the architecture: multiply-accumulates of one forward pass per layer kind "
      "(forward hooks on the reference's modules at batch 64; normalisations, activations and elementwise "
      "ops not counted), 2 FLOPs per MAC.")
    w("")
    w(f"- TemporalUnet forward, batch 64: {describe_macs(ref_alg1['macs']['diffusion'])} = "
      f"F_unet = {2 * unet / 1e9:.3f} GFLOP.")
    w(f"- Reward forward, batch 64: {describe_macs(ref_alg1['macs']['reward'])} = F_rho = {2 * rew / 1e9:.4f} GFLOP.")
    w(f"- Algorithm 1 step = 2 F_unet (base and expert, no-grad) + 6 F_rho (forward 1, input gradient with "
      f"create_graph 1, the double backward through both to the parameters 4) = {alg1_flops / 1e9:.3f} GFLOP.")
    w(f"- DDPM step = 3 F_unet (forward 1, backward 2) = {ddpm_flops / 1e9:.3f} GFLOP.")
    w(f"- Guided sampling of {n} trajectories = T x (F_unet + 2 F_rho) + F_rho (rho and its input gradient "
      f"per step, the final rho), with the forwards at batch {n} (F scales with the batch): "
      f"{big_t} x ({2 * unet_s / 1e9:.3f} + 2 x {2 * rew_s / 1e9:.4f}) + {2 * rew_s / 1e9:.4f} = {samp_flops / 1e9:.2f} GFLOP.")
    w(f"- Peak: {peak_text}.")
    w("")
    w("| benchmark | GFLOP per step | relreward GFLOP/s | % of peak | reference GFLOP/s | % of peak |")
    w("|---|---|---|---|---|---|")
    for label, flops, rr, ref in (
        ("Algorithm 1", alg1_flops, median(alg1_rr), median(alg1_ref)),
        ("DDPM training", ddpm_flops, median(ddpm_rr), median(ddpm_ref)),
        (f"guided sampling (per batch of {n})", samp_flops, 1e3 / (median(samp_rr) * n), 1e3 / (median(samp_ref) * n)),
    ):
        a, b = gflops(flops, rr), gflops(flops, ref)
        w(f"| {label} | {flops / 1e9:.3f} | {a:.1f} | {100 * a / peak:.0f}% | {b:.1f} | {100 * b / peak:.0f}% |")
    out.extend(compiled_section(runs, args.spread))
    w("")
    bars = [("Algorithm 1 steps/s", ratio_alg1, 1.0, " (aim 1.3)"), ("DDPM training steps/s", ratio_ddpm, 1.0, ""),
            ("guided sampling time per trajectory", ratio_samp, 1.0, "")]
    w("Against the issue's bars (at least 1.0x the reference): " + "; ".join(
        f"{name} {ratio:.2f}x, {'met' if ratio >= bar else '**missed**'}{aim}" for name, ratio, bar, aim in bars) + ".")
    print("\n".join(out))


if __name__ == "__main__":
    main()
