"""The ``ultron`` command line: thin wrappers that parse, call the library and print.

Each command imports the library inside its function, after its options are checked, so that
``ultron --help`` and a refused option answer in a fraction of a second instead of waiting
for torch (these are the only imports of ultron inside functions besides the phantom ↔ SDF
volume pair, :mod:`ultron.report`'s entry points, and optional or heavy third-party
libraries).
"""
