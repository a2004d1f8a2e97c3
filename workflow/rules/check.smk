# Validate each capture before anything is computed from it; its summary lists the scans.


checkpoint check_capture:
    input:
        capture=capture_input,
        code=code("crossline.io.capture"),
    output:
        summary="data/interim/{capture}/check.json",
    log:
        "logs/{capture}/check.log",
    resources:
        mem_mb=1000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline check data/raw/{wildcards.capture} --json {output.summary} > {log} 2>&1"
