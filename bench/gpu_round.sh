#!/usr/bin/env bash
# The GPU-machine figures of the training loop (issue 22) and the batch EGL renderer (issue 23), in
# one go, for a session that is lent a GPU host (one H100/H200, 16 cores). Run from the repository
# root with visfly-dist importable; every step writes its JSON as it ends, so a cut run keeps what
# it finished. Usage: OUT=/some/dir bash bench/gpu_round.sh   (default OUT: bench/results/gpu)
set -u
OUT="${OUT:-bench/results/gpu}"
PY="${PYTHON:-python3}"
mkdir -p "$OUT"
run() {  # run NAME CMD...: one benchmark, its output in NAME.log, its status in status.txt
  local name="$1"; shift
  echo "== $name: $*" | tee -a "$OUT/status.txt"
  timeout 900 "$PY" -m visfly_dist.cli "$@" > "$OUT/$name.log" 2>&1
  echo "   exit $?" | tee -a "$OUT/status.txt"
}
nvidia-smi -L > "$OUT/gpu.txt" 2>&1 || true
# The renderer first (minutes): 100 cameras, the batch egl pass against the per-camera one and the tracer.
run render bench render --backend egl egl-legacy raycast --res 64 256 --kinds depth rgb --agents 100 --reps 7 \
    --no-worker --moving 0 --json "$OUT/render.json"
# Workers sharing the cores: 1, 8 and 14 workers at 1,024 agents (goal: 8 and 14 >= 1.0x one).
run step-1024 bench step --agents 1024 --workers 1 8 14 --steps 60 --json "$OUT/step-1024.json"
run step-1024-egl bench step --agents 1024 --workers 1 --backend egl --steps 60 --json "$OUT/step-1024-egl.json"
# The training loop with no flags: the host plan (cuda, its agents, workers and threads), both trainers.
run train-plan bench train --timesteps 262144 --algo ppo sb3-ppo --json "$OUT/train-plan.json"
# The main job itself for 10 minutes of wall time (SIGINT: it saves final.zip), then its success on unseen garages.
timeout -s INT 600 "$PY" -m visfly_dist.cli train navigation --out "$OUT/nav" > "$OUT/nav.log" 2>&1
"$PY" -m visfly_dist.cli eval navigation --checkpoint "$OUT/nav/final.zip" --episodes 100 --seed 777 \
    --json "$OUT/nav-eval.json" >> "$OUT/nav.log" 2>&1
tar -C "$(dirname "$OUT")" -czf "$OUT.tar.gz" "$(basename "$OUT")"
