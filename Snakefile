# crossline: capture folders -> calibrations -> stripes -> points -> clouds -> reports
# (calibration certificate, accuracy report).
# A table of contents; the rules live in workflow/rules/, the code in the crossline package.
# Run: snakemake --cores 2  (the default profile in profiles/default supplies the rest).

from snakemake.utils import min_version

min_version("9.0")


configfile: "config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/check.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/scan.smk"
include: "workflow/rules/fuse.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/export.smk"


# Everything each listed capture allows (its check decides): the calibration certificate of
# a capture whose camera calibrates, and the accuracy report of one whose scans can be measured.
rule all:
    default_target: True
    input:
        *(targets_of(c) for c in config["captures"]),
