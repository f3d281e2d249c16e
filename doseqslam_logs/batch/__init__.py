"""Batch annotation: many logs, in parallel processes or on Ray, resumable via a manifest.

discovery (which logs, which output names) -> runner (what to redo, per the manifest) ->
an engine (local.py, ray_engine.py) running job.run_job per log -> manifest + report.
"""
