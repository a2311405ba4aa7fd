"""Evaluation of a trained avatar on held-out frames: the metrics (:mod:`.metrics`: the one PSNR and the one SSIM,
shared with the training loss), the report (:mod:`.report`), LPIPS (:mod:`.lpips`) and the figures (:mod:`.plot`:
training curves and the contact sheet, drawn with matplotlib from the ``train`` extra)."""
