"""Experiment: perturbation rounds that run one ladder per place of the worst tets.

Today a round (``jtet._perturb.perturb``) kicks all of its seeds (the tets within the
windows of the worst quality) at once, on one submesh around all of them, and judges
each attempt as a whole. On large meshes the seeds lie in several places that share no
vertex (the 983k-tet cube's late rounds: 4-12 places, submeshes of 3k-8k tets), an
attempt fails when one place ends worse, and a round ends on a single-site kick that
fixes one place (experiments/results/bench_improve.md, session 55).

Here a round instead takes the places one at a time, worst first: the seed tets chained
by shared vertices, on a submesh of their own (``RINGS`` vertex rings), with the
ladder, the judging (``_judge_round``) and the splice of a round today; places that
touch one already taken this round wait for the next round. A round counts as kept when
one of its places was kept. Every place pays the whole-mesh work of a round today
(seeds, neighbourhood sweeps, submesh, splice: ~70-110 ms at 983k tets): a built
version would do that once per round.

    PYTHONPATH=. python experiments/round_places.py --meshes gmsh:cube:0.03 --seeds 0,2
    PYTHONPATH=. python experiments/round_places.py --meshes gmsh:cube:0.0167 --seeds 0

Prints per run: wall time, climb and attempt seconds, attempts, places and rounds kept,
the final angles, and (attempt seconds, smallest dihedral angle) after kept attempts.
Run with ``JTET_HELPER=0`` for attempt counts that do not depend on timing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_improve import load_mesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

import jtet
from jtet import _helper_process
from jtet import _perturb as P
from jtet._submesh import Submesh

MAX_PLACES = 64  # places per round (a round whose kicks keep making new places ends)


def places(mesh, seeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids (s,), place (s,)): the seed tets and a label per seed tet; seed tets that
    share a vertex, directly or through other seed tets, share a label."""
    ids = np.flatnonzero(seeds)
    tets = mesh.tets[ids]
    rows = np.repeat(tets[:, :1], 3, axis=1).reshape(-1)
    graph = coo_matrix(
        (np.ones(len(rows), np.int8), (rows, tets[:, 1:].reshape(-1))),
        shape=(mesh.n_points, mesh.n_points),
    )
    label = connected_components(graph, directed=False)[1]
    return ids, label[tets[:, 0]]


def _sub_options(opts):
    return opts.replace(
        boundary="fixed",
        check=False,
        progress=False,
        goal_min_dihedral=None,
        goal_max_dihedral=None,
    )


def _place_round(run, t0, attempts, sub_opts, good, place_seeds, began) -> bool:
    """One place's ladder, judged and spliced as a round today; whether it kept one."""
    worst = float(run.q.min())
    part = Submesh(run.current, P._neighbourhood(run.current, place_seeds, P.RINGS))
    sel = part.sel
    state = P.RoundState(
        part.mesh, run.q[sel], run.lo_t[sel], run.hi_t[sel], sub_opts, worst, good, t0,
        place_seeds[sel],
    )  # fmt: skip
    baseline = P._Baseline(run.q, run.q[~sel], P.WINDOWS[0])
    ladder = _helper_process.Ladder(next(P._ROUND_IDS), len(attempts))
    helper = _helper_process.running()
    if helper is not None:
        helper.serve(state, attempts, ladder)
    try:
        kept = P._judge_round(run, t0, part, state, attempts, ladder, set(), baseline, began)
    finally:
        ladder.close()
    return kept is not None


def perturb_by_places(run, t0: float, rounds: int) -> str:
    """``jtet._perturb.perturb`` with one ladder per place (see the module docstring)."""
    opts = run.opts
    attempts = P.kicks(opts.ops, opts.insert)
    good = np.inf if opts.good_quality is None else opts.good_quality
    sub_opts = _sub_options(opts)
    kept_rounds = 0
    began = time.perf_counter()
    while kept_rounds < rounds and attempts:
        taken = np.zeros(run.current.n_points, bool)  # vertices of this round's places
        kept_any = False
        for _ in range(MAX_PLACES):
            seeds = P.round_seeds(run.current, run.q, good)
            if not seeds.any():
                break
            taken = np.concatenate([taken, np.zeros(run.current.n_points - len(taken), bool)])
            ids, place = places(run.current, seeds)
            touched = np.zeros(place.max() + 1, bool)
            np.logical_or.at(touched, place, taken[run.current.tets[ids]].any(axis=1))
            free = ~touched[place]
            if not free.any():
                break
            worst_place = place[free][np.argmin(run.q[ids][free])]
            mine = ids[place == worst_place]
            taken[run.current.tets[mine].reshape(-1)] = True
            place_seeds = np.zeros(run.current.n_tets, bool)
            place_seeds[mine] = True
            kept_any |= _place_round(run, t0, attempts, sub_opts, good, place_seeds, began)
        if not kept_any:
            return "converged"
        kept_rounds += 1
        run.check_goal()
    return "converged"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--meshes", default="gmsh_holeplate")
    p.add_argument("--seeds", default="0")
    p.add_argument("--modes", default="whole,places", help="whole (today's rounds), places")
    args = p.parse_args()
    today = P.perturb
    for name in args.meshes.split(","):
        jtet.improve(load_mesh(name), perturb=1)  # compiles this mesh's shapes
        for seed in map(int, args.seeds.split(",")):
            for mode in args.modes.split(","):
                P.perturb = perturb_by_places if mode == "places" else today
                try:
                    t = time.perf_counter()
                    r = jtet.improve(load_mesh(name), seed=seed)
                    wall = time.perf_counter() - t
                finally:
                    P.perturb = today
                kicks = [e for e in r.history if e["op"] == "perturb"]
                climb = sum(e["seconds"] for e in r.history if e["op"] != "perturb")
                spent, curve = 0.0, []
                for e in kicks:
                    spent += e["seconds"]
                    if e["successes"]:
                        curve.append(f"{spent:.1f}:{e['min_dihedral']:.2f}")
                kept = sum(e["successes"] for e in kicks)
                after = r.stats_after
                print(
                    f"{name} seed {seed} {mode}: {wall:.1f} s (climb {climb:.1f} s, attempts "
                    f"{spent:.1f} s), {len(kicks)} attempts, {kept} kept, "
                    f"{after.min_dihedral:.2f} / {after.max_dihedral:.2f}",
                    flush=True,
                )
                print("   attempt s:min dihedral after kept attempts:", " ".join(curve))


if __name__ == "__main__":
    main()
