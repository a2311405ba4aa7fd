"""Evaluation of a trained avatar on held-out frames: the report (:mod:`.report`), LPIPS (:mod:`.lpips`) and
plots (:mod:`.plot`)."""
