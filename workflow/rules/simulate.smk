# The virtual rig: renders a capture listed under `simulate:` when data/raw/<name> is missing.


rule simulate_capture:
    output:
        rig="data/raw/{capture}/rig.yaml",
    params:
        preset=lambda wc: SIMULATED[wc.capture].get("preset", "paper"),
        seed=lambda wc: SIMULATED[wc.capture].get("seed", 0),
        quick=lambda wc: "--quick" if SIMULATED[wc.capture].get("quick") else "",
        frames=lambda wc: (
            f"--frames {SIMULATED[wc.capture]['frames']}" if "frames" in SIMULATED[wc.capture] else ""
        ),
        pattern=lambda wc: ",".join(SIMULATED[wc.capture].get("pattern", ["A", "B", "AB"])),
    wildcard_constraints:
        capture="|".join(re.escape(c) for c in SIMULATED) or "(?!)",
    log:
        "logs/{capture}/simulate.log",
    threads: 2
    resources:
        mem_mb=4000,
    conda:
        "../envs/crossline.yaml"
    shell:
        "crossline simulate data/raw/{wildcards.capture} --preset {params.preset} "
        "--seed {params.seed} {params.quick} {params.frames} --pattern {params.pattern} "
        "--threads {threads} --force > {log} 2>&1"
