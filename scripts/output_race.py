"""Output race soak (issue 60): two runs started together for one output, and a file a user puts at --out while
a command runs. Each try must lose no result and replace nothing:

* ``run``: two ``dqm run --agents 2`` in one fresh folder (the default output): both exit 0, and
  ``dqm-out/run/`` holds ``clusters.npz`` and ``clusters-2.npz``, each named by one of the runs;
* ``match``: two ``dqm match FEATURES --out X.npz`` at once: every result is kept (two files, or one file
  and a one-line refusal, exit 2, that names where the other result went);
* ``user``: ``dqm match FEATURES --out X.npz`` while the user writes X.npz once the command checked it: the
  user's file is as written, the result is kept beside it, and the command says so in one line.

    python scripts/output_race.py --tries 20
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dqm import io, synthetic

PRECIOUS = b"precious\n"
#: a try of ``user`` where the command was done before the user wrote: no race, not counted
DONE_FIRST = "done first"


def dqm(*argv, cwd=None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dqm", *argv], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def try_run(work: Path) -> str:
    """'' if both results are kept, else what went wrong."""
    procs = [dqm("run", "--agents", "2", cwd=work) for _ in range(2)]
    said = [p.communicate(timeout=300) for p in procs]
    files = sorted(p.name for p in (work / "dqm-out" / "run").glob("*.npz"))
    named = sorted(name for out, _ in said for name in files if f"wrote dqm-out/run/{name} " in out)
    if [p.returncode for p in procs] != [0, 0] or files != ["clusters-2.npz", "clusters.npz"] or named != files:
        return f"exit codes {[p.returncode for p in procs]}, files {files}, named {named}: {said}"
    return ""


def try_match(work: Path, features: Path) -> str:
    out = work / "same.npz"
    procs = [dqm("match", str(features), "--out", str(out), "--quiet") for _ in range(2)]
    said = [p.communicate(timeout=300) for p in procs]
    codes = sorted(p.returncode for p in procs)
    files = sorted(p.name for p in work.glob("same*.npz"))
    refusals = [err for _, err in said if "appeared while this command ran" in err]
    if codes == [0, 0] or files != ["same-2.npz", "same.npz"] or (codes == [0, 2]) != (len(refusals) == 1):
        return f"exit codes {codes}, files {files}: {said}"
    if any(len(err.strip().splitlines()) != 1 for err in refusals):
        return f"a refusal of more than one line: {refusals}"
    return ""


def try_user(work: Path, features: Path, delay: float) -> str:
    out = work / "race.npz"
    p = dqm("match", str(features), "--out", str(out), "--quiet")
    time.sleep(delay)  # the check is done by then; the matching is not
    if p.poll() is not None:
        return f"ended before the user wrote: {p.communicate()}"
    out.write_bytes(PRECIOUS)
    _, err = p.communicate(timeout=300)
    if out.read_bytes() != PRECIOUS:
        return "the user's file was replaced"
    if p.returncode == 0 and not (work / "race-2.npz").exists():
        return DONE_FIRST  # it had written its result before the user wrote (then the user replaced it)
    if p.returncode != 2 or len(err.strip().splitlines()) != 1 or "race-2.npz" not in err:
        return f"exit {p.returncode}: {err}"
    if len(io.load_clusters(work / "race-2.npz")["labels"]) != len(io.load_features(features).image_ids):
        return "the kept result is not the whole result"
    return ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tries", type=int, default=20)
    ap.add_argument("--kinds", default="run,match,user")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="dqm-output-race-"))
    ds = synthetic.sized(150_000, seed=0)  # seconds of matching: the user writes while it runs
    features = root / "f.npz"
    io.save_features(features, io.FeatureSet(ds.descriptors, ds.image_ids))
    rows = []
    for kind in args.kinds.split(","):
        misses = skipped = 0
        for k in range(args.tries):
            work = root / f"{kind}{k}"
            work.mkdir()
            if kind == "run":
                why = try_run(work)
            elif kind == "match":
                why = try_match(work, features)
            else:
                why = try_user(work, features, 1.0 + 0.1 * (k % 5))
            if why == DONE_FIRST:
                print(f"{kind} try {k}: the command was done before the user wrote; not counted", flush=True)
                skipped += 1
                continue
            if why:
                misses += 1
                print(f"miss: {kind} try {k}: {why}", flush=True)
        rows.append((kind, args.tries - skipped, misses))
        print(f"{kind:6s} {args.tries - skipped} tries, {misses} misses", flush=True)
    print("\n| race | tries | results lost or replaced |\n|---|---|---|")
    for kind, tries, misses in rows:
        print(f"| {kind} | {tries} | {misses} |")
    return 1 if any(r[2] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
