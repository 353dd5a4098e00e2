"""Pre-training of the watermark decoders (behind ``gsw decoder train`` and ``gsw decoder export``).

Torch-only, like :mod:`gsw.decoder`: nothing here loads the compiled rasterizer (only the optional
refinement evaluation of :mod:`~gsw.decoder.pretrain.pipeline` imports :mod:`gsw.mark.refine`).

Modules:
    - :mod:`~gsw.decoder.pretrain.config`: :class:`TrainConfig`, :class:`MultiConfig` and shared constants.
    - :mod:`~gsw.decoder.pretrain.data`: photo loading, host crops, the device image bank.
    - :mod:`~gsw.decoder.pretrain.encoders`: template encoders, PSNR-scaled embedding, run encoders.
    - :mod:`~gsw.decoder.pretrain.loop`: the host-side trainer :func:`train` of one pair.
    - :mod:`~gsw.decoder.pretrain.multi`: the device-resident trainer :func:`train_multi` (the shipped decoders).
    - :mod:`~gsw.decoder.pretrain.whiten`: whitening fits of the trained decoders.
    - :mod:`~gsw.decoder.pretrain.evaluation`: attacks, unbiasedness, false positives.
    - :mod:`~gsw.decoder.pretrain.runs`: the run folder (``k{bits}.pt`` / ``k{bits}.json``).
    - :mod:`~gsw.decoder.pretrain.pipeline`: :func:`pretrain`, the whole ``gsw decoder train``.
    - :mod:`~gsw.decoder.pretrain.export`: weights + manifest + report (``gsw decoder export``).
    - :mod:`~gsw.decoder.pretrain.report`: the report's markdown.
"""
