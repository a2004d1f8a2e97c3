# The accuracy report of each capture: PDF for people, metrics.json for machines.


rule render_report:
    input:
        unpack(report_inputs),
        code=code("crossline.report.accuracy"),
    output:
        pdf="reports/{capture}/accuracy.pdf",
        metrics="reports/{capture}/metrics.json",
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
        "--pdf {output.pdf} --metrics {output.metrics} > {log} 2>&1"
