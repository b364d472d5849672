"""Every benchmark of the documentation in one run: each script a fresh process, one after the other.

The speed tables (the README's short one and the docs' performance page) come from one invocation of this script, so that their numbers share a
machine state. For each entry of :data:`SUITE` it records the command, the wall time, the machine's
load average (1-minute) just before and just after, and the script's output; it writes

* ``<out>/<name>.txt``: the output of each script (stdout, then stderr if any);
* ``<out>/run.json``: date, git commit, machine (CPU model and count, memory), and per script: command, exit
  code, wall, user and system seconds (the script's process and its children, from ``getrusage``), load
  before/after;
* ``<out>/run.md``: the same as a page (one section per script: command, load, output), the page the
  tables are transcribed from.

Scripts run in order with no overlap (the suite is a measurement, not a test: nothing is asserted).
A script that fails is recorded with its exit code and the suite goes on; the exit code of the suite is
the number of failed scripts (capped at 99).

Run by hand::

    python benchmarks/run_all.py                      # the whole suite, ~20 minutes on an idle machine
    python benchmarks/run_all.py --only limit online  # some entries
    python benchmarks/run_all.py --smoke              # every script's --smoke form, listed ones included (CI)

``src/`` is put first on ``PYTHONPATH`` so that the checkout's code is what runs.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

# (name, script, arguments of the full run, in the full run by default); the smoke run passes --smoke
# instead of the arguments and runs every entry (CI runs it: every benchmark script must be listed here,
# tests/test_benchmarks_suite.py checks that)
SUITE: list[tuple[str, str, list[str], bool]] = [
    ("limit", "bench_limit.py", [], True),
    ("core", "bench_core.py", [], True),
    ("stats", "bench_stats.py", [], True),
    ("all", "bench_all.py", [], True),
    ("fading", "bench_fading.py", ["--compiled-only"], True),
    ("protocol", "bench_protocol.py", ["--only-compiled"], True),
    ("online", "bench_online.py", [], True),
    ("memory", "bench_memory.py", [], True),
    ("scaling", "bench_scaling.py", ["--out", "{out}/bench_scaling"], True),
    ("adf", "bench_adf.py", [], True),
    ("simd", "bench_simd.py", [], True),
    ("particle", "bench_particle.py", [], True),
    ("nonlinear", "bench_nonlinear.py", [], True),
    ("sweep", "bench_sweep.py", ["--mem-runs", "10000", "1000000", "10000000", "--mem-scheduler", "processes"], True),
    # not speed benchmarks, or long: run with --only
    ("delay", "bench_delay.py", [], False),
    ("multichannel", "bench_multichannel.py", [], False),
    ("reliability", "bench_reliability.py", [], False),
    ("fit", "bench_fit.py", [], False),
]
NAMES = [name for name, *_ in SUITE]
DEFAULT = [name for name, *_, full in SUITE if full]


def _load() -> float:
    return os.getloadavg()[0]


def _commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
        )
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except OSError:  # pragma: no cover - no git
        return "unknown"


def _machine() -> str:
    """CPU model, logical CPUs and memory, e.g. ``Intel(R) Xeon(R) ... x 2, 23.5 GiB``."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:  # pragma: no cover - not Linux
        pass
    try:
        mem = f", {os.sysconf('SC_PHYS_PAGES') * os.sysconf('SC_PAGE_SIZE') / 2**30:.1f} GiB"
    except (AttributeError, OSError, ValueError):  # pragma: no cover - no sysconf
        mem = ""
    return f"{model} x {os.cpu_count()}{mem}"


def _children() -> tuple[float, float]:
    """User and system seconds of the finished children so far (each script's: the difference around it)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime, r.ru_stime


def run_suite(names: list[str], out: Path, smoke: bool) -> dict:
    """Run the entries ``names`` of :data:`SUITE` in order; write ``out``/*.txt, run.json, run.md."""
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT / "src") + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    record: dict = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "commit": _commit(),
        "cpus": os.cpu_count(),
        "machine": _machine(),
        "smoke": smoke,
        "python": sys.version.split()[0],
        "scripts": [],
    }
    for name, script, args, _ in SUITE:
        if name not in names:
            continue
        argv = ["--smoke"] if smoke else [a.format(out=out) for a in args]
        if smoke and name == "scaling":
            argv += ["--out", str(out / "bench_scaling")]
        cmd = [sys.executable, str(HERE / script), *argv]
        shown = " ".join(["python", f"benchmarks/{script}", *argv])
        print(f"[{name}] {shown}  (load {_load():.2f})", flush=True)
        before, t0, (u0, s0) = _load(), time.perf_counter(), _children()
        res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
        wall, after, (u1, s1) = time.perf_counter() - t0, _load(), _children()
        text = res.stdout + (f"\n--- stderr ---\n{res.stderr}" if res.stderr.strip() else "")
        (out / f"{name}.txt").write_text(text)
        entry = {
            "name": name,
            "command": shown,
            "returncode": res.returncode,
            "wall_s": round(wall, 1),
            "user_s": round(u1 - u0, 1),
            "sys_s": round(s1 - s0, 1),
            "load_before": round(before, 2),
            "load_after": round(after, 2),
        }
        record["scripts"].append(entry)
        print(
            f"[{name}] exit {res.returncode}, wall {wall:.0f} s (user {u1 - u0:.0f} s, system {s1 - s0:.0f} s), "
            f"load {before:.2f} -> {after:.2f}",
            flush=True,
        )
        if res.returncode != 0:  # the end of a failing script's output, for a CI log
            print("\n".join(text.rstrip().splitlines()[-30:]), flush=True)
    (out / "run.json").write_text(json.dumps(record, indent=2) + "\n")
    (out / "run.md").write_text(_page(record, out))
    return record


def _page(record: dict, out: Path) -> str:
    lines = [
        f"# Benchmark run {record['date']}",
        "",
        f"Commit {record['commit']}, Python {record['python']}, {record['machine']}"
        f"{', smoke sizes' if record['smoke'] else ''}. Every script a fresh process, in this order, none overlapping;",
        "user and system = CPU seconds of the script's process (all its threads and children); load = the 1-minute",
        "load average just before and just after the script (a wall time above user + system on a loaded machine is",
        "time spent waiting for a core).",
        "",
        "| script | command | exit | wall s | user s | system s | load before -> after |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in record["scripts"]:
        lines.append(
            f"| {e['name']} | `{e['command']}` | {e['returncode']} | {e['wall_s']} | {e['user_s']} | {e['sys_s']} | "
            f"{e['load_before']} -> {e['load_after']} |"
        )
    for e in record["scripts"]:
        lines += [
            "",
            f"## {e['name']}: `{e['command']}`",
            "",
            "```",
            (out / f"{e['name']}.txt").read_text().rstrip(),
            "```",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="every entry's --smoke form (CI)")
    ap.add_argument(
        "--only", nargs="+", choices=NAMES, default=None, help="entries to run (default: the entries of the full run)"
    )
    ap.add_argument("--out", default="results/benchmarks", help="output folder (default results/benchmarks)")
    args = ap.parse_args()
    names = args.only or (NAMES if args.smoke else DEFAULT)
    record = run_suite(names, Path(args.out).resolve(), args.smoke)
    failed = sum(e["returncode"] != 0 for e in record["scripts"])
    print(f"wrote {Path(args.out) / 'run.md'}; {failed} of {len(record['scripts'])} scripts failed")
    sys.exit(min(failed, 99))


if __name__ == "__main__":
    main()
