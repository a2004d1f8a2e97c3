# Scan stages: stripe centres (scattered over chunks of frames), then labels and 3-D points.
# With one chunk (the default) extraction writes the scan's stripe table itself; with more,
# each chunk writes a part and gather_stripes joins them (the same bytes either way).


rule extract_stripes:
    input:
        summary="data/interim/{capture}/check.json",
        frames=scan_frames_input,
        code=code("crossline.scan.stripes"),
    output:
        stripes=STRIPES_OUT,
    params:
        chunk=stripe_chunk,
        extractor=config["stripes"]["extractor"],
        threshold=config["stripes"]["threshold"],
        min_width=config["stripes"]["min_width"],
        max_width=config["stripes"]["max_width"],
        sigma=config["stripes"]["sigma"],
        pad=config["stripes"]["pad"],
        fit_pad=config["stripes"]["fit_pad"],
        relative_noise=config["stripes"]["relative_noise"],
        fit_across=config["stripes"]["fit_across"],
        min_peak=config["stripes"]["min_peak"],
        off_frames=config["stripes"]["off_frames"],
    log:
        f"logs/{{capture}}/extract_stripes/{STRIPES_TAG}.log",
    benchmark:
        f"logs/{{capture}}/benchmarks/extract_stripes/{STRIPES_TAG}.tsv"
    threads: 2
    resources:
        mem_mb=1000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline extract-stripes data/raw/{wildcards.capture} {wildcards.scan} "
        "--out {output.stripes} --extractor {params.extractor} --threshold {params.threshold} "
        "--min-width {params.min_width} --max-width {params.max_width} --sigma {params.sigma} "
        "--pad {params.pad} --fit-pad {params.fit_pad} --relative-noise {params.relative_noise} "
        "--fit-across {params.fit_across} --min-peak {params.min_peak} --off-frames {params.off_frames} "
        "--chunk {params.chunk} --threads {threads} > {log} 2>&1"


if CHUNKS > 1:

    rule gather_stripes:
        input:
            parts=stripe_chunks,
            code=code("crossline.scan.stripes"),
        output:
            stripes="data/interim/{capture}/stripes/{scan}.parquet",
        log:
            "logs/{capture}/gather_stripes/{scan}.log",
        resources:
            mem_mb=2000,
        conda:
            "../envs/crossline.yaml"
        shell:
            "crossline gather-stripes {input.parts} --out {output.stripes} > {log} 2>&1"


rule triangulate_points:
    input:
        stripes="data/interim/{capture}/stripes/{scan}.parquet",
        camera="data/interim/{capture}/calibration/camera.json",
        lasers="data/interim/{capture}/calibration/lasers.json",
        handeye="data/interim/{capture}/calibration/handeye.json",
        frames="data/raw/{capture}/scans/{scan}/frames.csv",
        code=code("crossline.scan.triangulate"),
    output:
        points="data/interim/{capture}/points/{scan}.parquet",
        stats="data/interim/{capture}/points/{scan}.json",
    params:
        threshold_px=config["points"]["threshold_px"],
        max_frame_gap=config["points"]["max_frame_gap"],
        ambiguity_px=config["points"]["ambiguity_px"],
        predict=config["points"]["predict"],
        end_trim_px=config["points"]["end_trim_px"],
        smooth_px=config["points"]["smooth_px"],
        bridge_columns=config["points"]["bridge_columns"],
        track_references=config["points"]["track_references"],
        sheet_curvature=config["points"]["sheet_curvature"],
    log:
        "logs/{capture}/triangulate_points/{scan}.log",
    benchmark:
        "logs/{capture}/benchmarks/triangulate_points/{scan}.tsv"
    resources:
        mem_mb=2000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline triangulate data/raw/{wildcards.capture} {wildcards.scan} "
        "--stripes {input.stripes} --camera {input.camera} --lasers {input.lasers} "
        "--handeye {input.handeye} --out {output.points} --threshold-px {params.threshold_px} "
        "--max-frame-gap {params.max_frame_gap} --ambiguity-px {params.ambiguity_px} "
        "--predict {params.predict} --end-trim-px {params.end_trim_px} "
        "--smooth-px {params.smooth_px} --bridge-columns {params.bridge_columns} "
        "--track-references {params.track_references} "
        "--sheet-curvature {params.sheet_curvature} "
        "--stats {output.stats} > {log} 2>&1"
