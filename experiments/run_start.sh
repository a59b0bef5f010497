#!/usr/bin/env bash
# A GPU run's time outside its steps (issue 32, item 3): `python -m evojax_morph.run --space
# bad_walker --steps 2 --chunk 1` three times on one machine, one after another: cold (empty JAX
# and Warp caches under OUT, so the run compiles everything), then warm with the warmup thread
# off (EVOJAX_MORPH_WARMUP=0) and on. Each run's timing.json goes to OUT/NAME.timing.json and a
# line to OUT/start.jsonl; a run already there is skipped, so the script resumes where a device
# call stopped.
#   bash experiments/run_start.sh OUT [RUN_ARGS ...]
#   bash experiments/run_start.sh /tmp/rs --num-envs 2 --train-steps 320 --confirm 2 \
#     --confirm-controllers 2 --horizon 2    # a CPU smoke run
set -uo pipefail
out=${1:?usage: run_start.sh OUT [RUN_ARGS ...]}; shift
mkdir -p "$out"
# faulthandler: a run that crashes (MuJoCo Warp has, docs/benchmarks.md) leaves its threads' stacks
export EVOJAX_MORPH_JAX_CACHE="$out/jax_cache" WARP_CACHE_PATH="$out/warp_cache" PYTHONFAULTHANDLER=1
start() {  # start NAME [ENV=VALUE ...]
  local name=$1; shift
  if [ -e "$out/$name.timing.json" ]; then echo "$name: done"; return; fi
  echo "$name: $(date +%T)"
  rm -rf "$out/run_$name"
  env "$@" timeout "${RUN_TIMEOUT:-560}" python -m evojax_morph.run --space bad_walker --steps 2 \
    --chunk 1 "${args[@]}" --out "$out/run_$name" > "$out/$name.log" 2>&1
  local rc=$?
  if [ $rc != 0 ]; then  # a crash is a result too: its line, then stop (a warm run after it
    # would compile what it left out of the cache); the script run again tries it again
    echo "$name: failed or timed out, rc $rc (see $out/$name.log)"
    echo "{\"run\": \"$name\", \"rc\": $rc}" >> "$out/start.jsonl"
    exit 1
  fi
  cp "$out/run_$name/timing.json" "$out/$name.timing.json"
  python -c "import json,sys; print(json.dumps({'run': sys.argv[1], **json.load(open(sys.argv[2]))}))" \
    "$name" "$out/$name.timing.json" >> "$out/start.jsonl"
}
args=("$@")
start cold
start warm_off EVOJAX_MORPH_WARMUP=0
start warm_on
python - "$out/start.jsonl" <<'PY'
import json, sys
for r in map(json.loads, open(sys.argv[1])):
    if "rc" in r:
        print(f"{r['run']:9} failed, rc {r['rc']}")
        continue
    print(f"{r['run']:9} outside the steps {r['outside_steps_seconds']} s, a step {r['step_seconds']} s,"
          f" first chunk returned after {r['first_chunk_dispatch']} s; {r['phases']}")
PY
