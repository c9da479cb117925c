"""Interleaved A/B of bench physics' rollout from two trees, timed by process CPU time (robust to
other processes on a shared machine) and wall time; best of reps, drone-seconds per second.

    git archive f9a2a03 visfly_dist | tar -x -C /tmp/before
    python docs/results/physics_ab.py /tmp/before . 5
"""
import sys, time, torch
torch.set_num_threads(1)
before_tree, after_tree = sys.argv[1], sys.argv[2]
reps = int(sys.argv[3]) if len(sys.argv) > 3 else 5
def load(root):
    for m in [k for k in sys.modules if k.startswith("visfly_dist")]: del sys.modules[m]
    sys.path.insert(0, root)
    import visfly_dist.bench.physics as p
    import visfly_dist.dynamics as d
    sys.path.pop(0)
    return p, d
trees = {"before": load(before_tree), "after": load(after_tree)}
res = {}
for rep in range(reps):
    for name, (p, d) in trees.items():
        for grad in (False, True):
            for n in (100, 1000):
                cfg = d.DynamicsConfig(controller="ctbr", ctrl_dt=0.02, sim_dt=0.005, integrator="rk4", motor_lag=True)
                quad = d.Quadrotor(cfg, "visfly", num_agents=n)
                action = quad.hover_action().expand(n, 4).contiguous()
                if grad: action = action.clone().requires_grad_()
                p._rollout(quad, action, 20, grad)
                c0, w0 = time.process_time(), time.perf_counter()
                p._rollout(quad, action, 100, grad)
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
                res.setdefault((n, grad, name), []).append((n * 100 * 0.02 / cpu, n * 100 * 0.02 / wall))
print(f"{reps} interleaved reps; best drone-s/s by CPU time (by wall time)")
print(f"{'agents':>6} {'grad':>5} {'before':>16} {'after':>16} {'ratio cpu (wall)':>18}")
for grad in (False, True):
    for n in (100, 1000):
        b = [max(x[i] for x in res[(n, grad, 'before')]) for i in (0, 1)]
        a = [max(x[i] for x in res[(n, grad, 'after')]) for i in (0, 1)]
        print(f"{n:>6} {str(grad):>5} {b[0]:>8.0f} ({b[1]:>5.0f}) {a[0]:>8.0f} ({a[1]:>5.0f}) {a[0]/b[0]:>8.2f} ({a[1]/b[1]:.2f})")
