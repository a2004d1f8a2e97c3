# Shared by all the .smk files: config validation, capture discovery, wildcard constraints and
# small input helpers. No rules here.

import json
import re
from pathlib import Path

from snakemake.utils import validate

from crossline.io.provenance import PACKAGE_ROOT, module_files


CAPTURE_NAME = r"[A-Za-z0-9_][A-Za-z0-9_.-]*"

# before the schema, which would say the same in the words of a JSON-schema pattern
for _name in config.get("captures") or []:
    if isinstance(_name, str) and not re.fullmatch(CAPTURE_NAME, _name):
        raise ValueError(
            f"config.yaml: capture name {_name!r} is not allowed: use letters, digits, "
            "'_', '-' and '.', no spaces or slashes"
        )

validate(config, "../schemas/config.schema.yaml")

SIMULATED = dict(config.get("simulate", {}))


wildcard_constraints:
    capture=CAPTURE_NAME,
    scan=r"[A-Za-z0-9_][A-Za-z0-9_.-]*",
    i=r"\d+",
    n=r"\d+",


def code(*modules):
    """Library sources a stage imports, declared as inputs so that editing them re-runs it.

    Paths are relative to the working directory when it holds the crossline sources (the
    repository root), else absolute paths into the installed package.
    """
    files = module_files(*modules)
    if all(Path(f).is_file() for f in files):
        return list(files)
    return [str(PACKAGE_ROOT.parent / f) for f in files]


def capture_input(wildcards):
    """What the check of a capture reads: rig.yaml of a simulated capture, else the folder."""
    if wildcards.capture in SIMULATED:
        return f"data/raw/{wildcards.capture}/rig.yaml"
    return f"data/raw/{wildcards.capture}"


def scans_of(capture):
    """Scan names of a capture, from its check summary (a checkpoint)."""
    summary = checkpoints.check_capture.get(capture=capture).output.summary
    return sorted(json.loads(Path(summary).read_text())["scans"])


def scan_frames_input(wildcards):
    """Inputs of a scan's stripe extraction: its table and its frame folder."""
    root = f"data/raw/{wildcards.capture}/scans/{wildcards.scan}"
    return [f"{root}/frames.csv", f"{root}/frames"]


def stripe_chunks(wildcards):
    """The chunk files gathered into one scan's stripe table."""
    n = config["stripes"]["chunks"]
    return [
        f"data/interim/{wildcards.capture}/stripes/{wildcards.scan}/part{i}-of-{n}.parquet"
        for i in range(n)
    ]


def report_inputs(wildcards):
    """Everything a capture's report reads: calibrations, points and clouds of every scan."""
    c = wildcards.capture
    scans = scans_of(c)
    return {
        "summary": f"data/interim/{c}/check.json",
        "camera": f"data/interim/{c}/calibration/camera.json",
        "lasers": f"data/interim/{c}/calibration/lasers.json",
        "handeye": f"data/interim/{c}/calibration/handeye.json",
        "points": [f"data/interim/{c}/points/{s}.parquet" for s in scans],
        "labels": [f"data/interim/{c}/points/{s}.json" for s in scans],
        "clouds": [f"data/processed/{c}/{s}.ply" for s in scans],
        "stats": [f"data/processed/{c}/{s}.fuse.json" for s in scans],
    }


def report_config():
    """Every parameter of every stage plus the tolerances, as the report's provenance (JSON)."""
    keys = ("camera", "lasers", "handeye", "stripes", "points", "fuse", "report")
    return json.dumps({k: config[k] for k in keys}, sort_keys=True)
