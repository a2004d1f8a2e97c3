# Exchange formats of the fused clouds (config export.formats): E57 for inspection software.


rule export_cloud:
    input:
        cloud="data/processed/{capture}/{scan}.ply",
        code=code("crossline.io.clouds"),
    output:
        e57="data/processed/{capture}/{scan}.e57",
    log:
        "logs/{capture}/export_cloud/{scan}.log",
    resources:
        mem_mb=2000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline export-cloud {input.cloud} --out {output.e57} > {log} 2>&1"
