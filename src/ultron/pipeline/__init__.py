"""The pipeline: a request → a run directory (mesh, volume, metrics, run.json, report), the
field cache, model files, presets, fine-tuning runs and the demo. Reads the method registry
(:mod:`ultron.methods.registry`); the CLI and the benchmark call it."""
