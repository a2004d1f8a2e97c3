# Shared by all the .smk files: config validation, capture discovery, wildcard constraints and
# small input helpers. No rules here.

import json
import re
import sys
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


def check_summary(capture):
    """A capture's check summary (check.json, the checkpoint's output) as a dict."""
    summary = checkpoints.check_capture.get(capture=capture).output.summary
    return json.loads(Path(summary).read_text())


STAGES = ("calibrate_camera", "calibrate_lasers", "calibrate_handeye", "scans")


def stages_of(summary):
    """Stage -> None if the capture allows it, else why not (the summary's ``stages``)."""
    stages = summary.get("stages")
    if isinstance(stages, dict):
        return {k: None if stages.get(k, {}).get("allowed") else
                (stages.get(k, {}).get("why") or "not allowed") for k in STAGES}
    # a summary written before the stages were listed: every stage, as then
    return dict.fromkeys(STAGES)


def scans_of(capture):
    """Scan names of a capture, from its check summary (a checkpoint)."""
    return sorted(check_summary(capture)["scans"])


def calibration_folders(wildcards, sets):
    """The capture's calibration folders among ``sets`` that hold views (per check.json)."""
    views = check_summary(wildcards.capture).get("views", {})
    return [f"data/raw/{wildcards.capture}/calibration/{k}" for k in sorted(views)
            if views[k] and any(k == s or (s.endswith("*") and k.startswith(s[:-1])) for s in sets)]


def camera_views_input(wildcards):
    """The board-view folders the camera calibrates on: camera/, or with views: all, every set."""
    sets = ["camera"] if config["camera"]["views"] == "camera" else ["camera", "laser_*", "handeye"]
    return calibration_folders(wildcards, sets)


def laser_views_input(wildcards):
    """The laser_<L> folders of the rig's lasers."""
    lasers = check_summary(wildcards.capture).get("lasers", ["A", "B"])
    return calibration_folders(wildcards, [f"laser_{x}" for x in lasers])


_TOLD = set()


def capture_targets(capture):
    """What the default target builds of a capture: what its stages allow.

    Every capture gets its check; one whose camera calibrates gets the calibration
    certificate; one whose scans can be measured also gets the accuracy report and its
    clouds in the export formats asked for. Stages the
    capture does not allow are said once, with the reason.
    """
    summary = check_summary(capture)
    why = stages_of(summary)
    if capture not in _TOLD:
        _TOLD.add(capture)
        for stage, reason in why.items():
            if reason:
                print(f"capture {capture}: {stage} not run: {reason}", file=sys.stderr)
    targets = [f"data/interim/{capture}/check.json"]
    if why["calibrate_camera"] is None:
        targets.append(f"reports/{capture}/calibration.pdf")
    if why["scans"] is None:
        targets.append(f"reports/{capture}/accuracy.pdf")
        targets += [f"data/processed/{capture}/{scan}.{fmt}" for fmt in export_formats()
                    for scan in sorted(summary["scans"])]
    return targets


def export_formats():
    """The cloud formats asked for besides PLY (config export.formats)."""
    return list((config.get("export") or {}).get("formats") or [])


def targets_of(capture):
    """An input function for one capture's default targets.

    The default target takes one such function per capture rather than one for them all:
    Snakemake waits for each input function's checkpoint separately, so with --keep-going a
    capture whose check fails does not hold back the captures listed after it.
    """
    return lambda wildcards: capture_targets(capture)


def certificate_inputs(wildcards):
    """The calibrations a capture's certificate shows: those the capture allows."""
    c = wildcards.capture
    why = stages_of(check_summary(c))
    out = {"summary": f"data/interim/{c}/check.json"}
    for stage, name in (("calibrate_camera", "camera"), ("calibrate_lasers", "lasers"),
                        ("calibrate_handeye", "handeye")):
        if why[stage] is None:
            out[name] = f"data/interim/{c}/calibration/{name}.json"
    return out


def certificate_args(wildcards, input):
    """The certificate command's calibration options, for the files it is given."""
    given = {k: getattr(input, k, None) for k in ("camera", "lasers", "handeye")}
    return " ".join(f"--{k} {v}" for k, v in given.items() if v)


def scan_frames_input(wildcards):
    """Inputs of a scan's stripe extraction: its table and its frame folder."""
    root = f"data/raw/{wildcards.capture}/scans/{wildcards.scan}"
    return [f"{root}/frames.csv", f"{root}/frames"]


CHUNKS = config["stripes"]["chunks"]
# what one extraction job writes: the scan's stripe table, or one chunk's part of it
STRIPES_OUT = (
    "data/interim/{capture}/stripes/{scan}.parquet"
    if CHUNKS == 1
    else "data/interim/{capture}/stripes/{scan}/part{i}-of-{n}.parquet"
)
STRIPES_TAG = "{scan}" if CHUNKS == 1 else "{scan}.part{i}-of-{n}"


def stripe_chunk(wildcards):
    """The ``--chunk i/n`` of one extraction job."""
    return f"{wildcards.i}/{wildcards.n}" if CHUNKS > 1 else "0/1"


def stripe_chunks(wildcards):
    """The chunk files gathered into one scan's stripe table."""
    return [
        f"data/interim/{wildcards.capture}/stripes/{wildcards.scan}/part{i}-of-{CHUNKS}.parquet"
        for i in range(CHUNKS)
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
        "arm": [f"data/processed/{c}/{s}.arm.npz" for s in scans],
    }


def report_config():
    """Every parameter of every stage plus the tolerances, as the report's provenance (JSON)."""
    keys = ("camera", "lasers", "handeye", "stripes", "points", "fuse", "report")
    return json.dumps({k: config[k] for k in keys}, sort_keys=True)


def certificate_config():
    """The calibrations' parameters and the certificate's limits, as JSON (its provenance)."""
    keys = ("camera", "lasers", "handeye", "certificate")
    return json.dumps({k: config[k] for k in keys}, sort_keys=True)
