"""Evaluation: the watermark report (:mod:`gsw.eval.report`), the method grid (:mod:`gsw.eval.grid`) and its plots."""
