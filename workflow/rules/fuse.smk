# Fused cloud of each scan (Open3D), base frame, mm.


rule fuse_points:
    input:
        points="data/interim/{capture}/points/{scan}.parquet",
        code=code("crossline.fuse"),
    output:
        cloud="data/processed/{capture}/{scan}.ply",
        stats="data/processed/{capture}/{scan}.fuse.json",
    params:
        neighbours=config["fuse"]["neighbours"],
        std_ratio=config["fuse"]["std_ratio"],
        voxel_mm=config["fuse"]["voxel_mm"],
        normal_radius_mm=config["fuse"]["normal_radius_mm"],
        mesh=config["fuse"]["mesh"],
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
        "--threads {threads} > {log} 2>&1"
