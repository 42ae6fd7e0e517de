"""``cosy run``: the whole pipeline (detect -> estimate -> match -> refine -> evaluate -> viz) in one
run folder, per scene, cached and resumable (:mod:`cosy_cli.pipeline.run_stage`)."""
