#!/usr/bin/env bash
# Fine-tuning runs side by side on one GPU, in device calls of under 10 minutes (the device tool).
# (The defaults: stages 13 and 13b, written in session 55 from GPU stage 12, installed then; session 54
# ran stages 12 and 12b; docs/training.md, "The next session with a GPU".)
#   bash configs/gpu_session.sh MINUTES [PLAN_SECONDS] [final]
# From the repository root on the GPU machine (torch with CUDA; no OpenImageIO needed). The runs
# (RUNS below, method:recipe:run folder) default to session 55's plan for a session with 15
# minutes of device time, one call on a fresh machine:
#   bash configs/gpu_session.sh 7 330 final        (device tool: carry [".cache/gpu/meshes"], timeout_s 590)
# which trains configs/ps_fcn_n_gpu_stage13.yaml and configs/ps_fcn_n_gpu_stage13b.yaml side by
# side (both from the installed PS-FCN+N, copied to .cache/gpu/ps_fcn_n_gpu12.pt when missing).
# Session 54 ran it with session 40's plan, stages 12 and 12b (from .cache/gpu/ps_fcn_n_gpu11.pt).
# Session 39 ran this command with session 33's plan, configs/ps_fcn_n_gpu_stage11.yaml and
# configs/ps_fcn_gpu_stage15_ir.yaml, on an H200 (380 s, rates 699 and 578 samples/s; start files
# .cache/gpu/ps_fcn_n_gpu10.pt and ps_fcn_avg14.pt = commit 4c60081's weights/ps_fcn_n.pt and
# weights/ps_fcn.pt). Session 33 ran that command with stages 10 and 14 (session 26's plan) on an H200 in 320 s,
# then, on the warm machine, RUNS="ps-fcn-n:configs/ps_fcn_n_gpu_stage10b.yaml:g_ps_fcn_n10b
# ps-fcn-n:configs/ps_fcn_n_gpu_stage10c.yaml:g_ps_fcn_n10c" INITS=ps_fcn_n_scale.pt:weights/ps_fcn_n.pt
# DEADLINE=250 FIRST=0.3 bash configs/gpu_session.sh 3 150 final (timeout_s 280; with FIRST=0.5
# and PLAN 180 the plan refused: a fifth of the planned samples was already past). Session 26
# ran configs/ps_fcn_n_gpu_stage9.yaml alone (this command, session 25's plan),
# then configs/ps_fcn_gpu_stage13.yaml alone (RUNS=... INITS=... IR_BENCH=0 DEADLINE=370
# FIRST=0.5 bash configs/gpu_session.sh 6 230 final, timeout_s 420). Session 14 ran configs/ps_fcn_gpu_stage8.yaml,
# configs/ps_fcn_n_gpu_stage6.yaml and configs/lcnet_gpu_stage6.yaml side by side in three calls
# (7.3 1200, 8.6 1200, 7.5 1200 final); session 17 started configs/ps_fcn_dagger_gpu_stage7.yaml,
# configs/lcnet_gpu_stage7_ir.yaml and configs/ps_fcn_n_gpu_stage8_ir.yaml (RUNS=... INITS=...).
# The first call checks CUDA with configs/tiny.yaml (and with interreflections when a run uses
# them), times the interreflection stream when IR_BENCH=1 (at most 45 s; session 26: 151 samples/s,
# far below a training run with them on the H100, 696: docs/performance.md),
# starts the runs, trains FIRST minutes (0.6), then sets each run's length from its own measured rate
# (samples = samples/s x PLAN_SECONDS x 0.9, lr halved every fifth, validation every fifteenth;
# the learning rate has not changed yet, so the run is as if started with those values) and trains
# on for the rest of MINUTES. A later call resumes them for MINUTES. Each call copies model.pt,
# state.json, stream.pt and the logs to $OUT (with 'final': best.pt as well, and with OPTIM=1 also the
# Adam state, so that a later session can continue the run exactly), in parts of 15 MB (the device tool returns
# files of at most 16 MB): unpack them into a folder of their own (docs/training.md), not over runs/. A run folder missing on the machine (a
# fresh machine) is restored from .cache/gpu/back/RUN (carried) with fresh Adam moments; RESUME=1
# refuses a call that would start the runs over instead.
set -u
cd "$(dirname "$0")/.."
DEVICE=${PSCTL_DEVICE:-cuda}  # cpu: tries the script here
MIN=${1:?minutes}; PLAN=${2:-1200}; FINAL=${3:-}
# FIRST: the first launch's minutes, before the plan; it must stay well under a fifth of PLAN's
# samples (the lr first halves there). DEADLINE: seconds from the start by which training stops,
# so that the files are packed and returned inside the device tool's call (its timeout_s): the
# minutes of each launch are cut to it, and a run still going 20 s before it (its setup, which
# --max-minutes does not count, took longer) gets SIGTERM, checkpoints and leaves
FIRST=${FIRST:-0.6}; DEADLINE=${DEADLINE:-530}
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT" runs .cache/gpu
export PYTHONUNBUFFERED=1 PSCTL_MESHES=$PWD/.cache/gpu/meshes OMP_NUM_THREADS=4
RUNS=${RUNS:-"ps-fcn-n:configs/ps_fcn_n_gpu_stage13.yaml:g_ps_fcn_n13 ps-fcn-n:configs/ps_fcn_n_gpu_stage13b.yaml:g_ps_fcn_n13b"}
PSCTL='import sys; from psctl.cli import main; sys.argv[0] = "psctl"; main()'
psctl() { python3 -c "$PSCTL" "$@"; }

# train.init (and the frozen LCNet) files: the release files of the commit the recipes name
# (session 14: ps_fcn_stage7.pt, ps_fcn_n_stage5.pt, lcnet_stage5.pt, from commit 0d58380/31049bb;
# session 17: ps_fcn_stage10.pt, ps_fcn_n_stage6.pt, lcnet_gpu6.pt; session 26: ps_fcn_n_miscal.pt,
# ps_fcn_stage12.pt)
INITS=${INITS:-"ps_fcn_n_gpu12.pt:weights/ps_fcn_n.pt"}
for i in $INITS; do [ -f .cache/gpu/${i%%:*} ] || cp ${i#*:} .cache/gpu/${i%%:*}; done
sha256sum .cache/gpu/*.pt .cache/gpu/meshes/* > "$OUT/inputs.sha256"

restore() {  # a fresh machine: the last returned state, without the optimiser's
  local name=$1
  [ -f runs/$name/state.json ] || [ ! -f .cache/gpu/back/$name/state.json ] || {
    cp -r .cache/gpu/back/$name runs/$name
    python3 - runs/$name/state.json <<'PY'
import json, sys
p = sys.argv[1]; st = json.load(open(p))
st["optim_files"] = []; st.setdefault("optim_reset_at", []).append(st["samples"])
json.dump(st, open(p, "w"), indent=1)
PY
  }
}

launch() {  # launch MINUTES: every run, side by side; wait for all
  local pids=() m c name
  for r in $RUNS; do
    IFS=: read -r m c name <<< "$r"
    restore $name
    # (checkpoint.json: a first checkpoint killed after its commit; --resume finishes it)
    if [ -f runs/$name/state.json ] || [ -f runs/$name/checkpoint.json ]; then a=(--resume runs/$name); else
      # a run that failed before its first checkpoint keeps its validated best.pt (psctl train
      # then refuses the folder): set it aside, with its log, and start the run again
      [ -f runs/$name/best.pt ] && mv runs/$name runs/$name.early-$SECONDS
      a=(--config $c --out runs/$name)
    fi
    # --max-minutes counts training only; the setup before it (the validation set, the first
    # pool; with interreflections both are slow) is not, so SIGTERM at the deadline as well:
    # the run checkpoints at its next step and leaves, and the files are still packed in time
    local cap=$((DEADLINE - SECONDS - 20)); [ $cap -ge 30 ] || cap=30
    timeout -s TERM -k 40 $cap python3 -c "$PSCTL" train $m "${a[@]}" --device $DEVICE --max-minutes $1 \
      >> runs/$name.out 2>&1 &
    pids+=($!)
  done
  local rc=0 c
  for p in "${pids[@]}"; do  # 124: stopped at the deadline, checkpointed (or its last checkpoint kept)
    wait $p; c=$?
    [ $c = 124 ] && echo "a run was stopped at the deadline ($SECONDS s since the start)"
    [ $c = 0 ] || [ $c = 124 ] || rc=1
  done
  return $rc
}

# fresh: some run has no state yet (here or carried back): check CUDA, launch, plan the runs not yet planned
# (checkpoint.json: a first checkpoint killed after its commit, which launch resumes)
stateless=(); for r in $RUNS; do n=${r##*:}
  [ -f runs/$n/state.json ] || [ -f runs/$n/checkpoint.json ] || [ -f .cache/gpu/back/$n/state.json ] || stateless+=($n); done
fresh=0; [ ${#stateless[@]} = 0 ] || fresh=1
# RESUME=1 (a later call): refuse to start the runs over. A machine stays warm 30 s after a call,
# so a later call usually gets a fresh one, which has no runs/ unless .cache/gpu/back was carried
# (helper-173: the runs started over under the same names, and their parts overwrote the longer ones)
if [ "${RESUME:-0}" = 1 ] && [ $fresh = 1 ]; then
  echo "RESUME=1 but no state of ${stateless[*]} here or in .cache/gpu/back (a fresh machine: carry .cache/gpu/back, docs/training.md)" | tee "$OUT/refused.txt"
  exit 2
fi
logs_out() { for r in $RUNS; do [ -f runs/${r##*:}.out ] && cp runs/${r##*:}.out "$OUT/"; done; }  # a failed call's logs come back
if [ $fresh = 1 ]; then
  nvidia-smi -L; python3 -c 'import torch; print("torch", torch.__version__, torch.cuda.get_device_name(0))'
  psctl train ps-fcn --config configs/tiny.yaml --device $DEVICE --out /tmp/tiny_$$ -q || exit 1
  # what the real runs use and tiny.yaml does not: bf16 autocast on CUDA and views of the carried
  # mesh (helper-173: first tried by the real runs, where a failure costs a whole launch)
  gpu_amp=bf16; [ $DEVICE = cpu ] && gpu_amp=none  # (bf16 on a CPU without it is refused)
  sed "s/shapes: {blobby: 1.0}}/shapes: {mesh: 1.0}, require_meshes: true}/; s/amp: none/amp: $gpu_amp/" \
    configs/tiny.yaml > /tmp/tiny_mesh.yaml
  psctl train ps-fcn --config /tmp/tiny_mesh.yaml --device $DEVICE --out /tmp/tiny_mesh_$$ -q || exit 1
  # the same with interreflections (their kernel runs on the stream's device), when a run uses them
  ir=0; for r in $RUNS; do IFS=: read -r m c name <<< "$r"; grep -q '^ *interreflection:' $c && ir=1; done
  if [ $ir = 1 ]; then
    sed 's/^data: {/data: {interreflection: {p: 1.0, albedo: [0.5, 0.9]}, /' configs/tiny.yaml > /tmp/tiny_ir.yaml
    psctl train ps-fcn --config /tmp/tiny_ir.yaml --device $DEVICE --out /tmp/tiny_ir_$$ -q || exit 1
  fi
  # the interreflection stream's speed on this device (IR_BENCH=1; session 26 measured it on an H100)
  [ "${IR_BENCH:-0}" = 0 ] || timeout 45 python3 benchmarks/bench_synth.py --device $DEVICE --skip pieces,writer \
    --batches 4 --warmup 1 --pool 16 --reuse 16 --interreflection 0.5 > "$OUT/ir_bench.txt" 2>&1 \
    || echo "ir bench: rc $? (45 s cap: 8 interreflection views did not fit)" >> "$OUT/ir_bench.txt"
  launch $FIRST || { for r in $RUNS; do tail -n 5 runs/${r##*:}.out; done; logs_out; exit 1; }
  names=(); for r in $RUNS; do names+=(runs/${r##*:}); done
  python3 - $PLAN "${names[@]}" > "$OUT/plan.txt" <<'PY' || { cat "$OUT/plan.txt"; for r in $RUNS; do tail -n 5 runs/${r##*:}.out; done; logs_out; exit 1; }
import json, statistics, sys
from pathlib import Path
plan = float(sys.argv[1])
for run in map(Path, sys.argv[2:]):
    if not (run / "state.json").is_file():
        sys.exit(f"{run.name}: no checkpoint after the first launch (its setup outlasted the deadline?): no plan")
    st = json.loads((run / "state.json").read_text())
    if "schedule_from_rate" in st:  # planned in an earlier call (a retry after one run failed)
        print(f"{run.name}: planned before ({st['schedule_from_rate']})"); continue
    recs = [json.loads(l) for l in open(run / "log.jsonl") if '"samples_per_s"' in l]
    if len(recs) >= 6:  # past the warm-up (the first third of the log lines)
        rate = statistics.median(r["samples_per_s"] for r in recs[len(recs) // 3:])
    else:  # a slow device: the whole minute
        rate = st["samples"] / st["seconds"]
    t = st["config"]["train"]
    unit = 5 * t["batch_size"]
    samples = max(int(rate * plan * 0.9) // unit * unit, 15 * unit)
    assert st["samples"] < samples // 5, "the learning rate would have changed already"
    t.update(samples=samples, lr_halve_every=samples // 5, val_every=samples // 15)
    st["schedule_from_rate"] = {"samples_per_s": rate, "plan_seconds": plan, "at_samples": st["samples"]}
    (run / "state.json").write_text(json.dumps(st, indent=1))
    print(f"{run.name}: {rate:.0f} samples/s in the first {st['seconds'] / 60:.1f} training minutes -> samples {samples:,}, "
          f"lr halved every {samples // 5:,}, validation every {samples // 15:,}")
PY
  cat "$OUT/plan.txt"
  left=$(python3 -c "print(max(0.5, $MIN - $FIRST))")
else
  left=$MIN
fi
left=$(python3 -c "print(round(max(0.5, min($left, ($DEADLINE - $SECONDS - 45) / 60)), 2))")  # 45 s: startup, last checkpoint
echo "training $left more minutes ($SECONDS s since the start)"
launch $left; rc=$?
for r in $RUNS; do tail -n 3 runs/${r##*:}.out; done
# a run SIGKILLed (timeout -k) inside a checkpoint's commit: carry it out, so the files packed are one checkpoint's
for r in $RUNS; do [ -d runs/${r##*:} ] && python3 -c 'import sys; from pathlib import Path; from psctl.checkpoint import finish_checkpoint; finish_checkpoint(Path(sys.argv[1]))' runs/${r##*:}; done
files="model.pt state.json stream.pt log.jsonl"
[ -n "$FINAL" ] && files="best.pt $files"  # the Adam state only with OPTIM=1: two runs with it pass the 64 MiB the device tool returns (session 33)
[ -n "$FINAL" ] && [ "${OPTIM:-0}" = 1 ] && files="$files optim.0.pt optim.1.pt optim.2.pt optim.3.pt"
list=(); for r in $RUNS; do n=${r##*:}; for f in $files; do [ -f runs/$n/$f ] && list+=(runs/$n/$f); done; list+=(runs/$n.out); done
tar -cf /tmp/runs.tar "${list[@]}" && split -b 15M /tmp/runs.tar "$OUT/runs.tar.part_" && rm /tmp/runs.tar
ls -la "$OUT"
exit $rc
