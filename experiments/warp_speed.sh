#!/usr/bin/env bash
# The rows of docs/benchmarks.md's Warp speed table (issue 32), one after another, each a
# `bench_fitness` process appending to OUT/rows.jsonl; a row already there is skipped, so the
# script resumes where a device call stopped. Logs go to OUT/NAME.log, traces to OUT/trace.
#   bash experiments/warp_speed.sh OUT [TRAIN_STEPS]    # TRAIN_STEPS: 10000, the standard budget
#   BW_B=2 CON_B=1 bash experiments/warp_speed.sh /tmp/ws 640    # a CPU smoke run
# Rows, XLA's deterministic GPU ops off as a `run` on Warp leaves them: Bad Walker at B = 1,024
# (Warp's graph captures counted), its learner's share (--update-epochs 1), its evaluation
# alone (--train-steps 0), the Constructor at B = 256; then a profile of each space at a short
# budget (--trace, 2 updates: a trace of a whole call was seen to run for minutes), last so
# that a slow trace costs no other row. A row that runs past ROW_TIMEOUT seconds (default 480)
# is stopped and not recorded. (Warp's staged graph mode, once a row here, ran at 0.43x the
# default's speed on an H100: docs/benchmarks.md.)
set -uo pipefail
out=${1:?usage: warp_speed.sh OUT [TRAIN_STEPS]}; steps=${2:-10000}
bw=${BW_B:-1024}; con=${CON_B:-256}  # the batch sizes of the two spaces' rows
mkdir -p "$out"
row() {  # row NAME BENCH_FITNESS_ARGS ...
  local name=$1; shift
  if grep -q "\"row\": \"$name\"" "$out/rows.jsonl" 2>/dev/null; then echo "$name: done"; return; fi
  echo "$name: $(date +%T)"
  rm -f "$out/$name.jsonl"
  timeout "${ROW_TIMEOUT:-480}" python -m experiments.bench_fitness \
    --physics warp --single 0 --repeats 2 --train-steps "$steps" \
    --out "$out/$name.jsonl" "$@" > "$out/$name.log" 2>&1 \
    || { echo "$name: failed or timed out (see $out/$name.log)"; return; }
  python -c "import json,sys; [print(json.dumps({'row': sys.argv[1], **json.loads(l)})) for l in open(sys.argv[2])]" \
    "$name" "$out/$name.jsonl" >> "$out/rows.jsonl"
}
row bad_walker --batches "$bw"
row bad_walker_epochs1 --batches "$bw" --update-epochs 1
row bad_walker_eval_only --batches "$bw" --train-steps 0
row constructor --space constructor --batches "$con"
row bad_walker_trace --batches "$bw" --train-steps 1280 --repeats 1 --trace "$out/trace/bw"
row constructor_trace --space constructor --batches "$con" --train-steps 1280 --repeats 1 \
  --trace "$out/trace/con"
python - "$out/rows.jsonl" <<'PY'
import json, sys
for r in map(json.loads, open(sys.argv[1])):
    t = r.get("trace") or {}
    kinds = " ".join(f"{k} {v:.0f}" for k, v in sorted(t.get("by_kind_ms", {}).items()))
    print(f"{r['row']:<20} B={r['batch']:<5} {r['evals_per_s']:8.1f} evals/s  ppo/phys "
          f"{r['ppo_over_physics']:.0%}  captures {r['warp_graph_captures']}"
          + (f"  busy/span {t['busy_ms']:.0f}/{t['span_ms']:.0f} ms  {kinds}" if t else ""))
PY
