# The reports of each capture, PDF for people and JSON for machines: the calibration
# certificate (any capture whose camera calibrates) and the accuracy report (captures with scans).


rule render_report:
    input:
        unpack(report_inputs),
        code=code("crossline.report.accuracy"),
    output:
        pdf="reports/{capture}/accuracy.pdf",
        metrics="reports/{capture}/metrics.json",
        deviation=directory("reports/{capture}/deviation"),
    params:
        config=report_config(),
    log:
        "logs/{capture}/render_report.log",
    benchmark:
        "logs/{capture}/benchmarks/render_report.tsv"
    resources:
        mem_mb=3000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline report data/raw/{wildcards.capture} --interim data/interim/{wildcards.capture} "
        "--processed data/processed/{wildcards.capture} --config-json {params.config:q} "
        "--pdf {output.pdf} --metrics {output.metrics} --deviation-dir {output.deviation} > {log} 2>&1"


rule calibration_certificate:
    input:
        unpack(certificate_inputs),
        code=code("crossline.report.certificate"),
    output:
        pdf="reports/{capture}/calibration.pdf",
        json="reports/{capture}/calibration.json",
    params:
        config=certificate_config(),
        calibrations=certificate_args,
    log:
        "logs/{capture}/calibration_certificate.log",
    benchmark:
        "logs/{capture}/benchmarks/calibration_certificate.tsv"
    resources:
        mem_mb=2000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline certificate data/raw/{wildcards.capture} --summary {input.summary} "
        "{params.calibrations} --config-json {params.config:q} "
        "--pdf {output.pdf} --json {output.json} > {log} 2>&1"
