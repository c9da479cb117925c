#!/usr/bin/env bash
# The GPU-machine figures of the training loop (issue 22) and the batch EGL renderer (issue 23) in
# one budgeted go, for a session lent a GPU host (one H100/H200, 16 cores) for a few minutes. Run
# from the repository root with visfly-dist importable (bench/gpu_bundle.sh). Each step has its own
# limit and the round ends within BUDGET_S; STEPS picks the steps and their order. After every step
# its log's end is printed, the logs and JSON rows are packed into $OUT/round.tgz and one line goes
# to $OUT/status.txt, so a cut run keeps what it finished.
#   OUT=/some/dir BUDGET_S=540 STEPS="train step render nav" bash bench/gpu_round.sh
# Steps: train (bench train with the host plan, both trainers), step (bench step at 256 and 1,024
# agents, 1 to 14 workers), render (100 cameras: batch egl, per-camera egl, tracer), nav (the main
# job with no flags for what time is left, at most NAV_LIMIT_S, then 100 deterministic episodes on
# unseen garages), step128 / step1024 (bench step at that many agents alone; step1024same with
# the same 56 scenes at 1, 8 and 14 workers), gputests (pytest of
# the tests that need a GPU), sections (the training thread's sections in the main job's configuration),
# profile (cProfile of the learner's main thread over a short default run), envsections (the env
# core alone per group step, bench/env_sections.py).
set -u
OUT="${OUT:-bench/results/gpu}"
PY="${PYTHON:-python3}"
BUDGET_S="${BUDGET_S:-540}"
STEPS="${STEPS:-train step render nav}"
WORK="$(mktemp -d)"
mkdir -p "$OUT"
START=$(date +%s)
left() { echo $(( BUDGET_S - ($(date +%s) - START) )); }
pack() { tar -C "$WORK" --exclude='*.zip' --exclude='videos' -czf "$OUT/round.tgz" . ; }
run() {  # run NAME LIMIT_S ARGS...: one visfly-dist command, SIGINT at its limit, its output in NAME.log
  local name="$1" limit="$2"; shift 2
  local remaining; remaining=$(left)
  if (( remaining < 25 )); then echo "== $name: skipped, ${remaining} s left" | tee -a "$OUT/status.txt"; return 1; fi
  (( limit > remaining )) && limit=$remaining
  echo "== $name (limit ${limit} s): visfly-dist $*" | tee -a "$OUT/status.txt"
  local t0; t0=$(date +%s)
  timeout -s INT -k 20 "$limit" "$PY" -m visfly_dist.cli "$@" > "$WORK/$name.log" 2>&1
  local rc=$?
  echo "   exit $rc after $(( $(date +%s) - t0 )) s" | tee -a "$OUT/status.txt"
  grep -v -E "^\[ +[0-9,]+/" "$WORK/$name.log" | tail -n 25 | cut -c1-400
  pack
  return $rc
}
step_train() {
  run train-plan 150 bench train --timesteps 131072 --algo ppo sb3-ppo --json "$WORK/train-plan.json"
}
step_gputests() {  # the tests that only a GPU runs (CUDA graphs, pinned copies)
  echo "== gputests: pytest of the CUDA tests" | tee -a "$OUT/status.txt"
  timeout -k 10 120 "$PY" -m pytest -q -p no:cacheprovider tests/training/test_graphed_policy.py \
      tests/training/test_device_stage.py tests/training/test_conv_pool.py \
      "tests/training/test_tensor_ppo.py::test_statistics_stay_beside_the_env_and_the_rollout_on_the_learners_device" \
      > "$WORK/gputests.log" 2>&1
  echo "   exit $?" | tee -a "$OUT/status.txt"
  tail -n 30 "$WORK/gputests.log"
  pack
}
step_sections() {  # the training thread's sections in the main job's configuration (bench/learner_sections.py)
  local limit; limit=$(left); (( limit > 100 )) && limit=100
  (( limit < 40 )) && { echo "== sections: skipped" | tee -a "$OUT/status.txt"; return; }
  echo "== sections (limit ${limit} s): bench/learner_sections.py --timesteps 131072" | tee -a "$OUT/status.txt"
  timeout -s INT -k 20 "$limit" "$PY" bench/learner_sections.py --timesteps 131072 --json "$WORK/sections.json" \
      > "$WORK/sections.log" 2>&1
  echo "   exit $?" | tee -a "$OUT/status.txt"
  grep -v -E "^video:" "$WORK/sections.log" | tail -n 26
  pack
}
step_envsections() {  # the env core alone per group step: the main job's groups of 64, and of 128 (bench/env_sections.py)
  local limit; limit=$(left); (( limit > 90 )) && limit=90
  (( limit < 40 )) && { echo "== envsections: skipped" | tee -a "$OUT/status.txt"; return; }
  echo "== envsections (limit ${limit} s): bench/env_sections.py --groups 2 --num-envs 128 / 256" | tee -a "$OUT/status.txt"
  for n in 128 256; do
    timeout -s INT -k 10 $(( limit / 2 )) "$PY" bench/env_sections.py --groups 2 --num-envs $n --steps 200 \
        --json "$WORK/envsections-$n.json" > "$WORK/envsections-$n.log" 2>&1
    echo "   $n agents: exit $?" | tee -a "$OUT/status.txt"
    tail -n 21 "$WORK/envsections-$n.log"
  done
  pack
}
step_step128() {  # the main job's agents on GPU hosts (the loop's ratio to the simulator)
  run step-128 45 bench step --agents 128 --workers 1 4 --steps 100 --json "$WORK/step-128.json"
}
step_step1024() {
  run step-1024 100 bench step --agents 1024 --workers 1 8 14 --steps 40 --json "$WORK/step-1024.json"
}
step_step1024same() {  # the same 56 scenes at every worker count: the workers' scaling, not the garages' spread
  run step-1024-same 90 bench step --agents 1024 --workers 1 8 14 --scenes 56 --steps 40 --json "$WORK/step-1024-same.json"
}
step_step() {
  run step-256 70 bench step --agents 256 --workers 1 4 --steps 60 --json "$WORK/step-256.json"
  run step-1024 100 bench step --agents 1024 --workers 1 8 14 --steps 40 --json "$WORK/step-1024.json"
}
step_render() {
  run render 60 bench render --backend egl egl-legacy raycast --res 64 256 --kinds depth rgb --agents 100 --reps 3 \
      --no-worker --moving 0 --json "$WORK/render.json" \
    || run render-legacy 60 bench render --backend egl-legacy raycast --res 64 256 --kinds depth rgb --agents 100 \
      --reps 3 --no-worker --moving 0 --json "$WORK/render-legacy.json"
}
step_nav() {
  local limit=$(( $(left) - 70 ))
  (( limit > ${NAV_LIMIT_S:-100000} )) && limit=$NAV_LIMIT_S
  run nav "$limit" train navigation --out "$WORK/nav"
  grep -E "^\[ +[0-9,]+/" "$WORK/nav.log" | tail -n 4
  run nav-eval 60 eval navigation --checkpoint "$WORK/nav/final.zip" --episodes 100 --seed 777 --mode deterministic \
      --json "$WORK/nav-eval.json"
}
step_profile() {
  local remaining; remaining=$(left)
  (( remaining < 60 )) && { echo "== profile: skipped" | tee -a "$OUT/status.txt"; return; }
  echo "== profile: cProfile of train navigation, 65,536 steps" | tee -a "$OUT/status.txt"
  timeout -s INT -k 20 90 "$PY" -m cProfile -o "$WORK/train.prof" -m visfly_dist.cli train navigation \
      --timesteps 65536 --video-every 0 --out "$WORK/prof" > "$WORK/profile.log" 2>&1
  "$PY" -c "import pstats, sys; s = pstats.Stats(sys.argv[1]); s.sort_stats('tottime').print_stats(25); \
s.sort_stats('cumulative').print_stats(35)" "$WORK/train.prof" > "$WORK/profile.txt" 2>&1
  grep -E "^ +[0-9]" "$WORK/profile.txt" | cut -c1-160 | head -n 60
  pack
}
{ nvidia-smi -L; nproc; "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"; } \
  > "$WORK/machine.txt" 2>&1
cat "$WORK/machine.txt"
for s in $STEPS; do "step_$s"; done
echo "round done after $(( $(date +%s) - START )) s" | tee -a "$OUT/status.txt"
