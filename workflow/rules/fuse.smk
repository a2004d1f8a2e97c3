# Fused cloud of each scan (Open3D), base frame, mm.


rule fuse_points:
    input:
        points="data/interim/{capture}/points/{scan}.parquet",
        # frame times and reported flange positions: the pose refinement's prior and centres
        frames="data/raw/{capture}/scans/{scan}/frames.csv",
        # its estimate of the arm's noise: the prior with arm_precision_mm auto
        handeye="data/interim/{capture}/calibration/handeye.json",
        code=code("crossline.fuse", "crossline.scan.refine", "crossline.calibrate.handeye"),
    output:
        cloud="data/processed/{capture}/{scan}.ply",
        stats="data/processed/{capture}/{scan}.fuse.json",
        arm="data/processed/{capture}/{scan}.arm.npz",
    params:
        neighbours=config["fuse"]["neighbours"],
        std_ratio=config["fuse"]["std_ratio"],
        voxel_mm=config["fuse"]["voxel_mm"],
        normal_radius_mm=config["fuse"]["normal_radius_mm"],
        mesh=config["fuse"]["mesh"],
        refine_poses=config["fuse"]["refine_poses"],
        arm_precision_mm=config["fuse"]["arm_precision_mm"],
        arm_precision_rad=config["fuse"]["arm_precision_rad"],
        arm_smooth_fraction=config["fuse"]["arm_smooth_fraction"],
        arm_corr_time_s=config["fuse"]["arm_corr_time_s"],
        crossing_half_mm=config["fuse"]["crossing_half_mm"],
        crossing_min_angle_deg=config["fuse"]["crossing_min_angle_deg"],
        crossing_max_width_ratio=config["fuse"]["crossing_max_width_ratio"],
        arm_draws=config["fuse"]["arm_draws"],
    log:
        "logs/{capture}/fuse_points/{scan}.log",
    benchmark:
        "logs/{capture}/benchmarks/fuse_points/{scan}.tsv"
    threads: 2
    resources:
        mem_mb=2000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline fuse {input.points} --out {output.cloud} --stats {output.stats} "
        "--neighbours {params.neighbours} --std-ratio {params.std_ratio} "
        "--voxel-mm {params.voxel_mm} --normal-radius-mm {params.normal_radius_mm} "
        "--mesh {params.mesh} --mesh-out data/processed/{wildcards.capture}/{wildcards.scan}.stl "
        "--refine-poses {params.refine_poses} --frames {input.frames} --handeye {input.handeye} "
        "--arm-precision-mm {params.arm_precision_mm} --arm-precision-rad {params.arm_precision_rad} "
        "--arm-smooth-fraction {params.arm_smooth_fraction} --arm-corr-time-s {params.arm_corr_time_s} "
        "--crossing-half-mm {params.crossing_half_mm} "
        "--crossing-min-angle-deg {params.crossing_min_angle_deg} "
        "--crossing-max-width-ratio {params.crossing_max_width_ratio} "
        "--arm-draws {params.arm_draws} --arm-draws-out {output.arm} "
        "--threads {threads} > {log} 2>&1"
