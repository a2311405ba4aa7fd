"""The command-line tools built on the library: the `blendsplat` commands (:mod:`.cli`), benchmarks
(:mod:`.bench`), random well-formed avatars (:mod:`.synth`, re-exporting :mod:`render_core.synthetic`), offline
rendering of driving files (:mod:`.offline`) and the demo (:mod:`.demo`). The top layer of the library: nothing in
render_core outside this package imports it (pyproject.toml's import-linter contracts check that)."""
