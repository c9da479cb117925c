"""Interleaved A/B(/C...) of bench physics' rollout from several source trees, timed by process CPU
time (robust to other processes on a shared machine) and wall time; best of reps, drone-seconds
per second, each tree's ratio to the first.

    git archive f9a2a03 visfly_dist | tar -x -C /tmp/original
    git archive 642741b visfly_dist | tar -x -C /tmp/previous
    python docs/results/physics_ab.py original=/tmp/original previous=/tmp/previous now=. --reps 5
"""
import argparse
import sys
import time

import torch

parser = argparse.ArgumentParser()
parser.add_argument("trees", nargs="+", help="NAME=PATH, the first is the reference")
parser.add_argument("--reps", type=int, default=5)
parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000])
args = parser.parse_args()
torch.set_num_threads(1)


def load(root):
    for m in [k for k in sys.modules if k.startswith("visfly_dist")]:
        del sys.modules[m]
    sys.path.insert(0, root)
    import visfly_dist.bench.physics as p
    import visfly_dist.dynamics as d
    sys.path.pop(0)
    return p, d


trees = {name: load(path) for name, path in (t.split("=", 1) for t in args.trees)}
res = {}
for rep in range(args.reps):
    for name, (p, d) in trees.items():
        for grad in (False, True):
            for n in args.agents:
                cfg = d.DynamicsConfig(controller="ctbr", ctrl_dt=0.02, sim_dt=0.005, integrator="rk4", motor_lag=True)
                quad = d.Quadrotor(cfg, "visfly", num_agents=n)
                action = quad.hover_action().expand(n, 4).contiguous()
                if grad:
                    action = action.clone().requires_grad_()
                p._rollout(quad, action, 20, grad)
                c0, w0 = time.process_time(), time.perf_counter()
                p._rollout(quad, action, 100, grad)
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                res.setdefault((n, grad, name), []).append((n * 100 * 0.02 / cpu, n * 100 * 0.02 / wall))
names = list(trees)
print(f"{args.reps} interleaved reps; best drone-s/s by CPU time (by wall time); ratio to {names[0]}")
print(f"{'agents':>6} {'grad':>5} " + " ".join(f"{n:>26}" for n in names))
for grad in (False, True):
    for n in args.agents:
        ref = [max(x[i] for x in res[(n, grad, names[0])]) for i in (0, 1)]
        cells = []
        for name in names:
            b = [max(x[i] for x in res[(n, grad, name)]) for i in (0, 1)]
            cells.append(f"{b[0]:>6.0f} ({b[1]:>5.0f}) {b[0] / ref[0]:>5.2f}x ({b[1] / ref[1]:.2f})")
        print(f"{n:>6} {str(grad):>5} " + " ".join(f"{c:>26}" for c in cells))
