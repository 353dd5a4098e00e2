"""Decoder pre-training (HiDDeN encoder/decoder pairs on photos, whitening, export of the shipped weights).

Behind ``gsw decoder train`` and ``gsw decoder export``.
"""
