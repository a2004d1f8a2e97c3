"""Run the benchmark scripts in this folder, then write docs/results.md from their results.

Each ``bench_*.py`` prints its figures and writes them under benchmarks/results/ (a ``.txt``
for people, a ``.json`` for programs). ``docs/results.md`` gathers the ``.txt`` files, one
section per area, each stamped with the commit that last wrote it, and the page with the
machine and the commit it was assembled at, so that no figure in the docs is typed by hand.

Usage:
    python benchmarks/run_all.py [name ...]     run the benchmarks whose names contain a name
                                                (all when none), then write docs/results.md
    python benchmarks/run_all.py --collect      only write docs/results.md from the results
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
OUT = REPO / "docs" / "results.md"

# results file stem -> (area, the command that writes it); files not listed come last
AREAS: dict[str, tuple[str, str]] = {
    "rigs": ("Accuracy on random rigs, every target", "python benchmarks/bench_rigs.py"),
    "rigs_20-39": ("Accuracy on random rigs 20-39, every target",
                   "python benchmarks/bench_rigs.py --seeds 20-39 --tag _20-39"),
    "rigs_40-51": ("Accuracy on random rigs 40-51, every target",
                   "python benchmarks/bench_rigs.py --seeds 40-51 --tag _40-51"),
    "rigs_52-59": ("Accuracy on random rigs 52-59, every target",
                   "python benchmarks/bench_rigs.py --seeds 52-59 --tag _52-59"),
    "rigs_random_0-3": ("Accuracy on random rigs of 1-12 MP (--preset random) 0-3, every target",
                        "python benchmarks/bench_rigs.py --preset random --seeds 0-3 --tag _random_0-3"),
    "arm_prior": ("The pose refinement's arm prior: stated or from the hand-eye views (random rigs 0-19)",
                  "python benchmarks/bench_arm_prior.py"),
    "calibration": ("Camera and laser planes against truth", "python benchmarks/bench_calibration.py"),
    "laser_planes": ("Laser planes on other boards, with and without the albedo gain",
                     "python benchmarks/bench_laser_planes.py"),
    "corners": ("Chessboard corners", "python benchmarks/bench_corners.py"),
    "handeye_seeds": ("Hand-eye over seeds", "python benchmarks/bench_handeye.py"),
    "handeye_noise": ("Hand-eye under arm noise", "python benchmarks/bench_handeye.py"),
    "scan": ("Scan stages: centre error, labels, speed as ratios to the decode bound",
             "python benchmarks/bench_scan.py"),
    "scale": ("Long scans: time and memory per stage", "python benchmarks/bench_scale.py"),
    "stripe_pairs": ("Stripe centres beside another stripe and the border",
                     "python benchmarks/bench_stripe_pairs.py"),
    "refine": ("Pose refinement over arm draws", "python benchmarks/bench_refine.py"),
    "refine_bias": ("Pose refinement: bias", "python benchmarks/bench_refine_bias.py"),
    "render": ("Rendering", "python benchmarks/bench_render.py"),
    "report": ("Report", "python benchmarks/bench_report.py"),
    "uncertainty": ("Coverage of the reports' U over seeded captures",
                    "python benchmarks/bench_uncertainty.py"),
    "posterior": ("Pose refinement's posterior against the error it leaves",
                  "python benchmarks/bench_posterior.py"),
    "jpeg": ("JPEG frames against PNG: camera, plane angle and point sigma",
             "python benchmarks/bench_jpeg.py"),
    "ball_bar": ("Ball bar: sphere-spacing error SD against truth", "python benchmarks/bench_ball_bar.py"),
    "sheet_curvature": ("Stripe centres of a thick sheet on a ball, corrected, against truth",
                        "python benchmarks/bench_sheet_curvature.py"),
    "speckle": ("Speckle: the renderer's field against coherent imaging and Dorsch's figure",
                "python benchmarks/bench_speckle.py"),
    "error_budget": ("Random rigs' ball and gauge errors: calibration against poses",
                     "python benchmarks/bench_error_budget.py --seeds 0-19"),
}


def _git(*args: str, path: Path = REPO) -> str:
    try:
        out = subprocess.run(["git", *args], cwd=path, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "?"
    return out.stdout.strip() or "?"


def machine() -> str:
    """One line naming the machine: CPU model, cores, memory, Python."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 2**20:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{mem}, Python {platform.python_version()}"


def _area(stem: str) -> tuple[str, str]:
    """The area and command of a results file: a listed stem, a run of a listed benchmark with
    ``--tag`` (``scale_arm``: bench_scale.py ... --tag _arm), or its notes (``scale_notes``)."""
    if stem in AREAS:
        return AREAS[stem]
    for key, (area, cmd) in AREAS.items():
        if stem.startswith(key + "_"):
            tag = stem[len(key):]
            if tag == "_notes":
                return f"{area}: notes", f"{cmd} (notes on its runs, each run's command inside)"
            return f"{area} ({tag[1:]})", f"{cmd} ... --tag {tag}"
    return stem, f"python benchmarks/bench_{stem}.py"


def collect() -> str:
    """The text of docs/results.md from the files in benchmarks/results/."""
    files = sorted(RESULTS.glob("*.txt"))
    order = {stem: i for i, stem in enumerate(AREAS)}
    files.sort(key=lambda p: (order.get(p.stem, len(order)), p.stem))
    lines = [
        "# Measured results",
        "",
        "Generated by `python benchmarks/run_all.py` (`--collect` to only gather) from",
        "`benchmarks/results/*.txt`; every figure here was printed by the benchmark named in",
        "its section. Do not edit by hand.",
        "",
        f"- assembled at commit `{_git('describe', '--always', '--dirty')}`",
        f"- on {machine()}",
        "",
        "Each section names the commit that last wrote its results file: figures of an older",
        "commit hold for that code; re-run the command to refresh them.",
        "",
    ]
    for p in files:
        area, cmd = _area(p.stem)
        written = _git("log", "-1", "--format=%h %cs", "--", str(p.relative_to(REPO)))
        if written == "?":
            written = "not committed yet"
        png = p.with_suffix(".png")
        lines += [f"## {area}", "", f"`{cmd}` → `benchmarks/results/{p.name}` ({written})", ""]
        if png.is_file():
            lines += [f"![{area}](../benchmarks/results/{png.name})", ""]
        lines += ["```", p.read_text().rstrip(), "```", ""]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    failed: list[str] = []
    if {"-h", "--help"} & set(argv):
        print(__doc__)
        return 0
    if "--collect" not in argv:
        scripts = sorted(HERE.glob("bench_*.py"))
        if argv:
            scripts = [s for s in scripts if any(n in s.stem for n in argv)]
            if not scripts:  # a typo would otherwise run nothing and rewrite the page
                print(f"no benchmark named like {' '.join(argv)}; they are: "
                      + ", ".join(s.stem for s in sorted(HERE.glob("bench_*.py"))))
                return 2
        for script in scripts:
            print(f"=== {script.name}", flush=True)
            t0 = time.perf_counter()
            rc = subprocess.call([sys.executable, str(script)], cwd=REPO)
            print(f"=== {script.name}: exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
            if rc:
                failed.append(script.name)
    OUT.write_text(collect())
    print(f"wrote {OUT.relative_to(REPO)}")
    if failed:
        print("failed:", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
