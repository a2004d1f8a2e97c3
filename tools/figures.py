"""Make the README's figures: the capture -> report flow (graphviz) and page 1 of a report.

Usage: python tools/figures.py [--report reports/demo/accuracy.pdf]
Needs graphviz's `dot` and poppler's `pdftoppm` (apt-get install graphviz poppler-utils).
Writes docs/figures/flow.svg and docs/figures/report_page1.png.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures"

# (node, label, kind): kind is the capture's input, a stage (a rule file) or an artefact
NODES = [
    ("capture", "capture folder\nrig.yaml, calibration/, scans/", "input"),
    ("check", "check\n(what the capture allows)", "stage"),
    ("camera", "calibrate camera\n(Zhang, bias-corrected)", "stage"),
    ("lasers", "calibrate lasers\n(planes from board poses)", "stage"),
    ("handeye", "calibrate hand-eye\n(AX = XB, refined)", "stage"),
    ("stripes", "extract stripes\n(chunks of frames)", "stage"),
    ("points", "triangulate\n(A / B labels, base frame)", "stage"),
    ("fuse", "fuse\n(pose refinement, outliers, normals)", "stage"),
    ("certificate", "calibration certificate\ncalibration.pdf + .json", "artefact"),
    ("cloud", "fused cloud\n<scan>.ply (.e57)", "artefact"),
    ("report", "accuracy report\naccuracy.pdf + metrics.json", "artefact"),
]
EDGES = [
    ("capture", "check"), ("check", "camera"), ("camera", "lasers"), ("camera", "handeye"),
    ("check", "stripes"), ("stripes", "points"), ("lasers", "points"), ("handeye", "points"),
    ("camera", "points"), ("points", "fuse"), ("fuse", "cloud"), ("cloud", "report"),
    ("camera", "certificate"), ("lasers", "certificate"), ("handeye", "certificate"),
]
STYLE = {
    "input": 'shape=folder, style=filled, fillcolor="#e8eef7"',
    "stage": 'shape=box, style="rounded,filled", fillcolor="#ffffff"',
    "artefact": 'shape=note, style=filled, fillcolor="#eef7e8"',
}


def flow_dot() -> str:
    """The DOT text of the flow diagram."""
    lines = ["digraph crossline {", '  rankdir=LR; bgcolor="white";',
             '  node [fontname="Helvetica", fontsize=10, penwidth=1.2];',
             '  edge [color="#666666", arrowsize=0.7];']
    for name, label, kind in NODES:
        text = label.replace("\n", "\\n")
        lines.append(f'  {name} [label="{text}", {STYLE[kind]}];')
    lines += [f"  {a} -> {b};" for a, b in EDGES]
    lines.append("}")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--report", type=Path, default=REPO / "reports" / "demo" / "accuracy.pdf")
    a = ap.parse_args(argv)
    FIGURES.mkdir(parents=True, exist_ok=True)
    for tool in ("dot", "pdftoppm"):
        if shutil.which(tool) is None:
            print(f"{tool} not found: apt-get install graphviz poppler-utils", file=sys.stderr)
            return 2
    svg = subprocess.run(["dot", "-Tsvg"], input=flow_dot(), capture_output=True, text=True,
                         check=True).stdout
    (FIGURES / "flow.svg").write_text(svg)
    print(f"wrote {(FIGURES / 'flow.svg').relative_to(REPO)}")
    if a.report.is_file():
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run(["pdftoppm", "-f", "1", "-l", "1", "-r", "60", "-png", str(a.report),
                            f"{tmp}/page"], check=True)
            page = next(Path(tmp).glob("page*.png"))
            shutil.copy(page, FIGURES / "report_page1.png")
        print(f"wrote {(FIGURES / 'report_page1.png').relative_to(REPO)}")
    else:
        print(f"{a.report} not found: run `make demo` first for the report page", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
