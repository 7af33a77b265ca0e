"""Why reward guidance does or does not add to plan selection: numbers on the planner's own samples.

Module map: `load` (the base and expert planners, the trained rho rebuilt in PyTorch from
steer.py's work directory by bench.py's `torch_reward`), `fit` (per denoising step t, on the base
planner's own x_t (current state inpainted, as when planning) and on data windows noised by
q(x_t | x_0) (as Algorithm 1 trains): the cosine between grad rho and the target mu_expert -
mu_base, over the free entries and over the executed first action, the relative error
||grad rho - target|| / ||target|| (over both as well), and the guidance step omega ||grad rho|| against the
denoising step ||mu_base - x_t||), `separation` (AUC of rho(x_t, t) between expert and
medium-replay windows, at every t), `actions` (how far the expert planner's first action is
from the base planner's, against the spread of the base's own plans: what choosing among the
plans can reach), `shift` (how much of the
base -> expert first-action gap guidance closes at each omega, by grad rho and by the true
difference), `asymmetry` (whether the target mu_expert - mu_base can be a gradient at all: the
antisymmetric share of its Jacobian, and which blocks carry it), `oracle` (closed-loop episodes on sweep seeds guided by the true difference
mu_expert - mu_base in place of grad rho: what a perfect rho gradient would add at this omega).

    python experiments/locomotion/diagnose.py --env hopper --data steer-out/data --work steer-out/hopper
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import relreward
from bench import torch_reward
from common import ENVS, PLANNERS, normalized_score
from planner import GUIDE_AT, Planner, _denoise, act_many, run_episodes, sample
from steer import start_server


def load(a):
    base = Planner.load(a.planners / f"{a.env}-medium-replay")
    expert = Planner.load(a.planners / f"{a.env}-expert")
    # steer.py's results when it has finished; its reward is stored under this name from the start.
    path = a.work / f"{a.env}-results.json"
    res = json.loads(path.read_text()) if path.exists() else dict(omega=1.0, t_stopgrad=0)
    # The stored reward, downloaded from a server started on steer.py's data directory.
    server = start_server(a.work / "server-data")
    try:
        with relreward.Client(server.addr) as client:
            rho = torch_reward(client, a.reward or f"{a.env}-reward")
    finally:
        server.stop(grace=30)
    return base, expert, rho, res


def grad_rho(rho, x: np.ndarray, t: int) -> np.ndarray:
    xt = torch.tensor(x, dtype=torch.float32, requires_grad=True)
    (g,) = torch.autograd.grad(rho(xt, torch.full((len(x),), t, dtype=torch.int64)).sum(), xt)
    return g.numpy().astype(np.float64)


def rho_value(rho, x: np.ndarray, t: int) -> np.ndarray:
    with torch.no_grad():
        return rho(torch.tensor(x, dtype=torch.float32), torch.full((len(x),), t, dtype=torch.int64)).numpy()


def mean_diff(base: Planner, expert: Planner, x: np.ndarray, t: int) -> np.ndarray:
    """mu_expert - mu_base at x_t: the posterior means differ only through the clipped x0."""
    return base.sched.coef1[t] * (np.clip(_denoise(expert, x, t), -1, 1) - np.clip(_denoise(base, x, t), -1, 1))


def cos(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, v = u.reshape(len(u), -1), v.reshape(len(v), -1)
    return (u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1) + 1e-12)


def windows(p: Planner, path: Path, n: int, rng) -> np.ndarray:
    w = p.windows(dict(np.load(path)))
    return w[rng.choice(len(w), size=min(n, len(w)), replace=False)].astype(np.float64)


def fit(base, expert, rho, win, omega, rng) -> list[dict]:
    """Per t: how well grad rho matches its target on the planner's path and on q(x_t | x_0)."""
    A, s = base.act_dim, base.sched
    cond = win[:, 0, A:]
    free = np.ones(win.shape[1:], bool)
    free[0, A:] = False  # the inpainted current state: guidance there is overwritten
    x = rng.standard_normal(win.shape)
    x[:, 0, A:] = cond
    rows = []
    for t in reversed(range(s.T)):
        row = dict(t=t)
        noised = s.sqrt_abar[t] * win + s.sqrt_1m_abar[t] * rng.standard_normal(win.shape)
        for label, xt in (("planner", x), ("q", noised)):
            g, d = grad_rho(rho, xt, t), mean_diff(base, expert, xt, t)
            row[f"{label}_cos_free"] = float(np.mean(cos(g[:, free], d[:, free])))
            row[f"{label}_cos_action"] = float(np.mean(cos(g[:, 0, :A], d[:, 0, :A])))
            row[f"{label}_rel_err"] = float(np.linalg.norm(g[:, free] - d[:, free]) / np.linalg.norm(d[:, free]))
            row[f"{label}_rel_err_action"] = float(np.linalg.norm(g[:, 0, :A] - d[:, 0, :A]) / np.linalg.norm(d[:, 0, :A]))
            row[f"{label}_grad_norm"] = float(np.linalg.norm(g[:, free], axis=1).mean())
            row[f"{label}_target_norm"] = float(np.linalg.norm(d[:, free], axis=1).mean())
        # The base planner's own step from x (no noise), against omega * grad rho there.
        x0 = np.clip(_denoise(base, x, t), -1, 1)
        mu = s.coef1[t] * x0 + s.coef2[t] * x
        g = grad_rho(rho, x, t)
        row["guide_over_denoise"] = float(omega * np.linalg.norm(g[:, free], axis=1).mean()
                                          / np.linalg.norm((mu - x)[:, free], axis=1).mean())
        rows.append(row)
        x = mu + (np.exp(0.5 * s.log_var[t]) * rng.standard_normal(x.shape) if t > 0 else 0.0)
        x[:, 0, A:] = cond
    return rows


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(rho(expert) > rho(medium-replay)), ties counted half (Mann-Whitney)."""
    allv = np.concatenate([pos, neg])
    order = np.argsort(allv, kind="mergesort")
    ranks = np.empty(len(allv))
    ranks[order] = np.arange(1, len(allv) + 1)
    # Tied values share their mean rank (so a tie counts half).
    _, inv, counts = np.unique(allv, return_inverse=True, return_counts=True)
    ranks = (np.bincount(inv, weights=ranks) / counts)[inv]
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def separation(base, rho, win_b, win_e, rng) -> dict:
    s, A, out = base.sched, base.act_dim, {}
    for t in range(s.T):
        vals = []
        for w in (win_e, win_b):
            xt = s.sqrt_abar[t] * w + s.sqrt_1m_abar[t] * rng.standard_normal(w.shape)
            xt[:, 0, A:] = w[:, 0, A:]
            vals.append(rho_value(rho, xt, t))
        out[t] = auc(*vals)
    return out


def actions(base, expert, win, n_plans: int, seed: int) -> dict:
    """Distances in normalised action units, from data states of the base planner's data."""
    A = base.act_dim
    st = win[:, 0, A:]
    pb = sample(base, st, n_plans, [seed + i for i in range(len(st))])
    base_plans = pb.reshape(len(st), n_plans, *pb.shape[1:])[:, :, 0, :A]
    pe = sample(expert, st, 1, [seed + 10_000 + i for i in range(len(st))])[:, 0, :A]
    first = base_plans[:, 0]
    nearest = np.min(np.linalg.norm(base_plans - pe[:, None], axis=2), axis=1)
    spread = np.linalg.norm(base_plans - base_plans.mean(1, keepdims=True), axis=2).mean()
    return dict(expert_vs_first_plan=float(np.linalg.norm(pe - first, axis=1).mean()),
                expert_vs_nearest_of_plans=float(nearest.mean()), base_plans_spread=float(spread))


def shift(base, expert, rho, win, omegas, t_stopgrad: int, seed: int, guide_at: str) -> list[dict]:
    """How far guidance moves the executed first action toward the expert planner's, per omega:
    the share of the base -> expert gap closed (projection of the move on the gap, over the
    gap's squared length, averaged over states), for grad rho and for the true difference."""
    A = base.act_dim
    st = win[:, 0, A:]
    seeds = [seed + i for i in range(len(st))]
    first = lambda x: x[:, 0, :A]  # noqa: E731  (n_plans = 1: row i is state i's plan)
    a_b = first(sample(base, st, 1, seeds))
    # The expert with the same noise: then the exact difference at omega 1 closes the gap exactly.
    a_e = first(sample(expert, st, 1, seeds))
    gap = a_e - a_b
    out = []
    for om in omegas:
        row = dict(omega=om)
        for label, gfn in (("grad_rho", lambda x, t: grad_rho(rho, x, t)),
                           ("true_difference", lambda x, t: mean_diff(base, expert, x, t))):
            mv = first(sample(base, st, 1, seeds, gfn, om, t_stopgrad, guide_at=guide_at)) - a_b
            row[f"{label}_gap_closed"] = float(np.mean((mv * gap).sum(1) / (gap ** 2).sum(1)))
            row[f"{label}_move"] = float(np.linalg.norm(mv, axis=1).mean())
        out.append(row)
    return out


def asymmetry(base, expert, win, ts, rng) -> list[dict]:
    """How far the target field mu_expert - mu_base is from any gradient field, per t, at data
    windows noised by q(x_t | x_0): a gradient's Jacobian is symmetric, so the share
    ||J - J^T|| / (2 ||J||) of its antisymmetric part is 0 for a field grad rho can match and
    about 0.71 for a Jacobian with no symmetry at all (as for a random matrix). Also the norms of
    the blocks d(first action) / d(current state) and d(current state) / d(first action): a
    planner that reads its action off the state (the policy part) gives the first and not the
    second, which no gradient can (its two blocks are each other's transpose)."""
    A, s = base.act_dim, base.sched
    D = win.shape[2]
    rows = []
    for t in ts:
        tt = torch.full((1,), t, dtype=torch.int64)

        def target(x, t=t, tt=tt):
            return float(s.coef1[t]) * (expert.net(x[None], tt).clamp(-1, 1) - base.net(x[None], tt).clamp(-1, 1))[0]
        shares, act_state, state_act = [], [], []
        for w in win:
            x0 = torch.tensor(w, dtype=torch.float32)
            xt = float(s.sqrt_abar[t]) * x0 + float(s.sqrt_1m_abar[t]) * torch.tensor(rng.standard_normal(w.shape),
                                                                                      dtype=torch.float32)
            n = xt.numel()
            J = torch.autograd.functional.jacobian(lambda x: target(x.reshape(xt.shape)).reshape(-1), xt.reshape(-1))
            J = J.reshape(n, n).double()
            shares.append(float((J - J.T).norm() / (2 * J.norm() + 1e-30)))
            Jb = J.reshape(*xt.shape, *xt.shape)
            act_state.append(float(Jb[0, :A, 0, A:].norm()))
            state_act.append(float(Jb[0, A:D, 0, :A].norm()))
        rows.append(dict(t=t, antisymmetric_share=float(np.mean(shares)),
                         d_action_d_state=float(np.mean(act_state)), d_state_d_action=float(np.mean(state_act))))
    return rows


def oracle(a, base, expert, rho, omega: float) -> dict:
    """Normalised returns of episodes on sweep seeds, every arm choosing its plan by rho except
    the unsteered one: unsteered, select-only, guided by grad rho, guided by the true
    difference mu_expert - mu_base (a perfect rho), with a.guide_at, a.t_stopgrad and
    a.guide_t_max."""
    seeds = list(range(a.seed_base, a.seed_base + a.episodes))
    def upto(f):  # guidance only at t <= a.guide_t_max (the steps where rho fits best)
        return lambda x, t: f(x, t) if t <= a.guide_t_max else np.zeros_like(x)
    arms = (("unsteered", None, 0.0), ("select", None, 0.0),
            ("grad_rho", upto(lambda x, t: grad_rho(rho, x, t)), omega),
            ("true_difference", upto(lambda x, t: mean_diff(base, expert, x, t)), omega))
    out = {}
    for label, gfn, om in arms:
        sel = None if label == "unsteered" else (lambda x: rho_value(rho, x, 0))

        def decide(obs, sd, step, gfn=gfn, sel=sel, om=om):
            return act_many(base, obs, 16, [v * 100_003 + step for v in sd], gfn, om, a.t_stopgrad, sel, a.guide_at)
        eps = run_episodes(lambda: gym.make(ENVS[a.env]["id"], max_episode_steps=a.max_steps), decide, seeds,
                           a.max_steps)
        out[label] = [round(float(normalized_score(a.env, e["ret"])), 3) for e in eps]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True, choices=sorted(ENVS))
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--work", type=Path, required=True, help="steer.py's --work directory (its trained reward)")
    p.add_argument("--planners", type=Path, default=PLANNERS)
    p.add_argument("--reward", help="the stored reward's name (default: steer.py's, ENV-reward)")
    p.add_argument("--n", type=int, default=256, help="windows per statistic")
    p.add_argument("--omega", type=float, help="default: the omega steer.py chose")
    p.add_argument("--t-stopgrad", type=int, default=0, help="for the gap-closing measure")
    p.add_argument("--guide-at", default="mean", choices=GUIDE_AT, help="the oracle episodes' guidance rule")
    p.add_argument("--guide-t-max", type=int, default=10**6, help="oracle episodes: no guidance above this t")
    p.add_argument("--episodes", type=int, default=0, help="oracle episodes per arm (sweep seeds)")
    p.add_argument("--seed-base", type=int, default=10_000, help="the sweep's seeds, never the reported ones")
    p.add_argument("--max-steps", type=int, default=300)
    a = p.parse_args()
    torch.set_num_threads(1)
    base, expert, rho, res = load(a)
    omega = a.omega if a.omega is not None else res["omega"]
    rng = np.random.default_rng(0)
    win_b = windows(base, a.data / f"{a.env}-medium-replay.npz", a.n, rng)
    win_e = windows(base, a.data / f"{a.env}-expert.npz", a.n, rng)
    out = dict(env=a.env, omega=omega, t_stopgrad=res["t_stopgrad"], fit=fit(base, expert, rho, win_b, omega, rng),
               separation_auc=separation(base, rho, win_b, win_e, rng),
               actions=actions(base, expert, win_b[:64], 16, 1),
               target_asymmetry=asymmetry(base, expert, win_b[:16], (0, 2, 10, base.sched.T - 1), rng),
               shift={g: shift(base, expert, rho, win_b[:64], (0.3, 1.0, 3.0), a.t_stopgrad, 2, g) for g in GUIDE_AT})
    if a.episodes:
        out["oracle"] = oracle(a, base, expert, rho, omega)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
