"""The command-line tools built on the library: the `blendsplat` commands (:mod:`.cli`), benchmarks
(:mod:`.bench`), random well-formed avatars (:mod:`.synth`), offline rendering of driving files (:mod:`.offline`)
and the demo (:mod:`.demo`). Nothing in the library proper depends on this package except tests and self-checks."""
