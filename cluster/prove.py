"""Run the workflow on one capture locally and on Slurm; check sacct and byte identity.

Called by `cluster/local-slurm.sh run [quick|demo] [--tree]` once the cluster is up. Both runs
use one snapshot of the sources, HEAD's (or the working tree's with --tree; PYTHONPATH points
the stages at its crossline package) in one folder, one after the other, so that paths and code
are the same and only the executor differs:

1. `snakemake --cores 2` (the default profile): its artefacts move to <work>/local;
2. `snakemake --workflow-profile profiles/slurm` from scratch (the capture is rendered again);
3. sacct lists every Slurm job of that run (the plugin names them all after its run id and
   writes rule and wildcards into the comment): one per non-local rule instance of the run,
   the same instances as the local run, all COMPLETED with exit code 0;
4. every file under data/ and reports/ (rendered frames, JSON, parquet, PLY, PDF) has the same
   sha256 in both runs.

Exits 1 if a check fails. Writes <work>/sacct.txt, <work>/sha256-{local,slurm}.txt and
<work>/summary.txt.
"""

from __future__ import annotations

import argparse
import collections
import datetime as dt
import hashlib
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ARTEFACT_DIRS = ("data", "reports")
RULE_HEAD = re.compile(r"^(local)?(rule|checkpoint) (\w+):$")
SACCT_FIELDS = "JobID,Comment%70,State,ExitCode,Elapsed,AllocCPUS,ReqMem,Timelimit,Partition,Account"


def snapshot(dest: Path, tree: bool, rev: str = "HEAD") -> None:
    """Copy the sources committed at rev, or with tree the working tree's, to dest."""
    if not tree:
        archive = subprocess.run(["git", "archive", rev], cwd=REPO, check=True, capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
        for top in ARTEFACT_DIRS:
            shutil.rmtree(dest / top, ignore_errors=True)
        return
    names = (
        subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            check=True,
            capture_output=True,
        )
        .stdout.decode()
        .split("\0")
    )
    for name in sorted(n for n in names if n):
        src = REPO / name
        if name.split("/")[0] in (*ARTEFACT_DIRS, "logs") or not src.is_file():
            continue
        out = dest / name
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, out)


def run(cmd: list[str], cwd: Path, env: dict, log: Path) -> float:
    """Run cmd with its output in log; seconds taken; exit on failure with the log's tail."""
    print(f"$ {' '.join(cmd)}  (in {cwd}, log {log})", flush=True)
    t0 = time.monotonic()
    with log.open("w") as fh:
        rc = subprocess.run(cmd, cwd=cwd, env=env, stdout=fh, stderr=subprocess.STDOUT).returncode
    seconds = time.monotonic() - t0
    if rc != 0:
        sys.stdout.write("".join(log.read_text().splitlines(keepends=True)[-40:]))
        sys.exit(f"FAILED ({rc}) after {seconds:.0f} s: {' '.join(cmd)}")
    print(f"  done in {seconds:.0f} s", flush=True)
    return seconds


def jobs_of(log: Path) -> list[tuple[str, str, str]]:
    """(where, rule, wildcard values joined by '_') of every job a Snakemake log announces."""
    jobs, current = [], None
    for line in [*log.read_text().splitlines(), ""]:
        head = RULE_HEAD.match(line)
        if head:
            current = ["local" if head.group(1) else "remote", head.group(3), ""]
            jobs.append(current)
        elif current is not None and line.startswith("    wildcards: "):
            pairs = line.split(": ", 1)[1].split(", ")
            current[2] = "_".join(p.split("=", 1)[1] for p in pairs)
        elif not line.startswith("    "):
            current = None
    return sorted(tuple(j) for j in jobs)


def comment_of(rule: str, wildcards: str) -> str:
    """The comment the Slurm executor plugin gives a rule instance's job."""
    return f"rule_{rule}_wildcards_{wildcards}" if wildcards else f"rule_{rule}"


def hashes(root: Path) -> dict[str, str]:
    """sha256 of every file under root's artefact folders, by relative path."""
    out = {}
    for top in ARTEFACT_DIRS:
        for path in sorted((root / top).rglob("*")):
            if path.is_file():
                out[str(path.relative_to(root))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def main() -> int:
    """Both runs and the checks; 0 when all pass."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", choices=["quick", "demo"], help="cluster/<capture>.yaml")
    parser.add_argument(
        "--status-seconds",
        type=int,
        default=5,
        help="plugin's wait before the first status check and between checks",
    )
    parser.add_argument(
        "--tree",
        action="store_true",
        help="run the working tree's sources (uncommitted edits included) instead of HEAD",
    )
    parser.add_argument("--rev", default="HEAD", help="the commit whose sources run (default HEAD)")
    args = parser.parse_args()

    work = Path(os.environ.get("CROSSLINE_SLURM_WORK", "/tmp/crossline-slurm")) / args.capture
    src, local = work / "src", work / "local"
    if work.exists():
        shutil.rmtree(work)
    src.mkdir(parents=True)
    snapshot(src, args.tree, args.rev)
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(
            [str(src)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        ),
    )
    where = subprocess.run(
        [sys.executable, "-c", "import crossline; print(crossline.__file__)"],
        cwd=src,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    if not where.startswith(str(src)):
        sys.exit(f"the snapshot's crossline is not the one imported ({where})")
    configfile = f"cluster/{args.capture}.yaml"
    smk = [sys.executable, "-m", "snakemake", "--configfile", configfile]

    t_local = run([*smk, "--cores", "2"], src, env, work / "local.log")
    local.mkdir()
    for top in (*ARTEFACT_DIRS, "logs"):
        if (src / top).exists():
            shutil.move(src / top, local / top)
    shutil.rmtree(src / ".snakemake", ignore_errors=True)

    start = dt.datetime.now() - dt.timedelta(minutes=1)
    t_slurm = run(
        [
            *smk,
            "--workflow-profile",
            "profiles/slurm",
            "--slurm-init-seconds-before-status-checks",
            str(args.status_seconds),
            "--slurm-keep-successful-logs",
        ],
        src,
        env,
        work / "slurm.log",
    )
    text = (work / "slurm.log").read_text()
    found = re.search(r"SLURM run ID: (\S+)", text)
    if not found:
        sys.exit("no 'SLURM run ID' in the Slurm run's log")
    run_id = found.group(1)
    base = ["sacct", "-X", "--name", run_id, "--starttime", start.strftime("%Y-%m-%dT%H:%M:%S")]
    table = subprocess.run(
        [*base, "--format", SACCT_FIELDS], check=True, capture_output=True, text=True
    ).stdout
    (work / "sacct.txt").write_text(table)
    rows = subprocess.run(
        [*base, "-n", "-P", "--format", "JobID,Comment,State,ExitCode"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    records = [r.split("|") for r in rows if r]

    failures = []
    local_jobs, slurm_jobs = jobs_of(work / "local.log"), jobs_of(work / "slurm.log")
    if [j[1:] for j in local_jobs] != [j[1:] for j in slurm_jobs]:
        failures.append(f"job lists differ: local {local_jobs} vs slurm {slurm_jobs}")
    expected = collections.Counter(comment_of(r, w) for where_, r, w in slurm_jobs if where_ == "remote")
    got = collections.Counter(rec[1] for rec in records)
    if expected != got:
        failures.append(f"sacct jobs {dict(got)} != the run's remote jobs {dict(expected)}")
    bad = [rec for rec in records if rec[2] != "COMPLETED" or rec[3] != "0:0"]
    if bad:
        failures.append(f"sacct jobs not COMPLETED 0:0: {bad}")

    h_local, h_slurm = hashes(local), hashes(src)
    for name, h in (("local", h_local), ("slurm", h_slurm)):
        (work / f"sha256-{name}.txt").write_text("".join(f"{v}  {k}\n" for k, v in h.items()))
    by_ext = collections.Counter()
    same_ext = collections.Counter()
    for path in sorted(set(h_local) | set(h_slurm)):
        ext = Path(path).suffix.lstrip(".") or "(none)"
        by_ext[ext] += 1
        same_ext[ext] += h_local.get(path) is not None and h_local.get(path) == h_slurm.get(path)
    differing = sorted(p for p in set(h_local) | set(h_slurm) if h_local.get(p) != h_slurm.get(p))
    if differing:
        failures.append(f"{len(differing)} files differ or are missing: {differing[:20]}")

    per_rule = collections.Counter(r for w, r, _ in slurm_jobs if w == "remote")
    lines = [
        f"capture: {configfile} (work folder {work})",
        f"local run (--cores 2): {t_local:.0f} s; Slurm run: {t_slurm:.0f} s",
        f"Slurm run id: {run_id}",
        f"Snakemake jobs: {len(slurm_jobs)} ({sum(per_rule.values())} on Slurm, "
        f"{len(slurm_jobs) - sum(per_rule.values())} local: "
        f"{', '.join(r for w, r, _ in slurm_jobs if w == 'local') or 'none'})",
        "  per rule: " + ", ".join(f"{r} {n}" for r, n in sorted(per_rule.items())),
        f"sacct jobs: {len(records)} "
        f"({sum(rec[2] == 'COMPLETED' and rec[3] == '0:0' for rec in records)} COMPLETED 0:0)",
        f"artefacts compared: {len(h_local)} local, {len(h_slurm)} Slurm; "
        f"byte-identical: {sum(same_ext.values())}",
        "  by type: " + ", ".join(f"{e} {same_ext[e]}/{n}" for e, n in sorted(by_ext.items())),
        "sacct:",
        table.rstrip(),
        "RESULT: " + ("PASS" if not failures else "FAIL"),
    ] + [f"  {f}" for f in failures]
    summary = "\n".join(lines) + "\n"
    (work / "summary.txt").write_text(summary)
    print(summary, end="")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
