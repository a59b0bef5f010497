"""Same keys, same fitness? `em.evaluate` in fresh processes, under several XLA flag sets.

Each flag set runs in --processes fresh Python processes (no compilation cache, so each compiles
and autotunes anew); each process evaluates the same --batch random Bad Walker bodies with the
same keys, twice (the first call compiles). Reported per flag set: the largest difference between
the two calls of one process (same compiled program), between processes (same code and keys,
a new compile), how many bodies differ by more than 1e-3, and the seconds of one call against
the default flags' (the cost of determinism). A walking gait turns any rounding difference into
another controller, so a nondeterministic op shows as fitness differences of tens.

  python -m experiments.check_determinism                         # GPU
  python -m experiments.check_determinism --batch 4 --train-steps 320 --processes 2   # CPU smoke
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

FLAG_SETS = {
    "default": "",
    "deterministic": "--xla_gpu_deterministic_ops=true",
    "deterministic_no_autotune": "--xla_gpu_deterministic_ops=true --xla_gpu_autotune_level=0",
}


def child(batch: int, train_steps: int, controllers: int) -> None:
    import jax

    import evojax_morph as em

    jax.config.update("jax_default_matmul_precision", "highest")
    space = em.make_space("bad_walker")
    cfg = em.FitnessConfig(ppo=em.standard_ppo(train_steps, controllers))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
    calls, seconds = [], []
    for _ in range(2):  # the first call compiles
        start = time.perf_counter()
        calls.append(np.asarray(em.evaluate(space, morphs, keys, cfg).fitness).tolist())
        seconds.append(time.perf_counter() - start)
    print(
        "RESULT "
        + json.dumps({"calls": calls, "seconds": seconds[1], "compile_and_run": seconds[0]})
    )


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--train-steps", type=int, default=10_000)
    parser.add_argument("--controllers", type=int, default=1)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--flags", nargs="+", default=list(FLAG_SETS), choices=list(FLAG_SETS))
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help="a JSON file for the results")
    args = parser.parse_args(argv)
    if args.child:
        return child(args.batch, args.train_steps, args.controllers)
    results = {}
    for name in args.flags:
        env = dict(
            os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + FLAG_SETS[name]).strip()
        )
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        runs = []
        for _ in range(args.processes):
            cmd = [
                sys.executable,
                "-m",
                "experiments.check_determinism",
                "--child",
                "--batch",
                str(args.batch),
                "--train-steps",
                str(args.train_steps),
                "--controllers",
                str(args.controllers),
            ]
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if proc.returncode:
                print(f"{name}: a process failed:\n{proc.stderr[-2000:]}", flush=True)
                break
            runs.append(json.loads(proc.stdout.split("RESULT ")[1]))
        if len(runs) < args.processes:
            continue
        calls = np.array([r["calls"] for r in runs])  # (processes, 2, batch)
        within = np.abs(calls[:, 0] - calls[:, 1]).max()
        across = np.abs(calls[0, 0] - calls[1:, 0]).max() if args.processes > 1 else float("nan")
        differ = (
            int((np.abs(calls[0, 0] - calls[1:, 0]) > 1e-3).any(0).sum())
            if args.processes > 1
            else 0
        )
        results[name] = {
            "xla_flags": FLAG_SETS[name],
            "within_process_max_diff": float(within),
            "across_processes_max_diff": float(across),
            "bodies_differing": differ,
            "seconds_per_call": float(np.median([r["seconds"] for r in runs])),
            "compile_and_first_call_s": float(np.median([r["compile_and_run"] for r in runs])),
        }
        print(name, json.dumps(results[name]), flush=True)
    base = results.get("default", {}).get("seconds_per_call")
    print(
        f"\n{'flags':<28} {'within':>10} {'across':>10} {'differing':>9} {'s/call':>8} {'cost':>6}"
    )
    for name, r in results.items():
        cost = f"{r['seconds_per_call'] / base:.2f}x" if base else "-"
        print(
            f"{name:<28} {r['within_process_max_diff']:>10.3g} "
            f"{r['across_processes_max_diff']:>10.3g} "
            f"{r['bodies_differing']:>5}/{args.batch:<3} {r['seconds_per_call']:>8.2f} {cost:>6}"
        )
    if args.out:
        import jax

        meta = {
            "device": jax.devices()[0].device_kind,
            "jax": jax.__version__,
            "batch": args.batch,
            "train_steps": args.train_steps,
            "controllers": args.controllers,
            "date": time.strftime("%Y-%m-%d"),
        }
        with open(args.out, "w") as f:
            json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
