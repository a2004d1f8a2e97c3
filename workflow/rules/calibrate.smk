# Calibration: camera intrinsics, the rig's laser planes (A, or A and B), and the hand-eye
# transform X. Each runs only on what the capture holds (check.json lists it).


rule calibrate_camera:
    input:
        summary="data/interim/{capture}/check.json",
        # the folders that hold views: with views: all, the lasers-off board views of the
        # laser and hand-eye sets count too (a capture may lack any of them)
        views=camera_views_input,
        code=code("crossline.calibrate.camera"),
    output:
        camera="data/interim/{capture}/calibration/camera.json",
    params:
        views=config["camera"]["views"],
        bias_correction=config["camera"]["bias_correction"],
        outlier_factor=config["camera"]["outlier_factor"],
        min_views=config["camera"]["min_views"],
        distortion=config["camera"]["distortion"],
    log:
        "logs/{capture}/calibrate_camera.log",
    benchmark:
        "logs/{capture}/benchmarks/calibrate_camera.tsv"
    threads: 2
    resources:
        mem_mb=3000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline calibrate-camera data/raw/{wildcards.capture} --out {output.camera} "
        "--bias-correction {params.bias_correction} --outlier-factor {params.outlier_factor} "
        "--min-views {params.min_views} --views {params.views} --distortion {params.distortion} "
        "--threads {threads} > {log} 2>&1"


rule calibrate_lasers:
    input:
        summary="data/interim/{capture}/check.json",
        camera="data/interim/{capture}/calibration/camera.json",
        views=laser_views_input,  # laser_<L>/ of each of the rig's lasers (A, or A and B)
        code=code("crossline.calibrate.lasers"),
    output:
        lasers="data/interim/{capture}/calibration/lasers.json",
    params:
        threshold=config["lasers"]["threshold"],
        trim=config["lasers"]["trim"],
        margin_px=config["lasers"]["margin_px"],
    log:
        "logs/{capture}/calibrate_lasers.log",
    benchmark:
        "logs/{capture}/benchmarks/calibrate_lasers.tsv"
    threads: 2
    resources:
        mem_mb=3000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline calibrate-lasers data/raw/{wildcards.capture} --camera {input.camera} "
        "--out {output.lasers} --threshold {params.threshold} --trim {params.trim} "
        "--margin-px {params.margin_px} "
        "--threads {threads} > {log} 2>&1"


rule calibrate_handeye:
    input:
        summary="data/interim/{capture}/check.json",
        camera="data/interim/{capture}/calibration/camera.json",
        views="data/raw/{capture}/calibration/handeye",
        code=code("crossline.calibrate.handeye"),
    output:
        handeye="data/interim/{capture}/calibration/handeye.json",
    params:
        mismatch_k=config["handeye"]["mismatch_k"],
    log:
        "logs/{capture}/calibrate_handeye.log",
    benchmark:
        "logs/{capture}/benchmarks/calibrate_handeye.tsv"
    threads: 2
    resources:
        mem_mb=3000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline calibrate-handeye data/raw/{wildcards.capture} --camera {input.camera} "
        "--out {output.handeye} --mismatch-k {params.mismatch_k} "
        "--threads {threads} > {log} 2>&1"
