"""The 3D-GSW method: messages, frequency-guided densification, the gradient mask, the losses, embedding
(:mod:`gsw.mark.embed`), detection (:mod:`gsw.mark.detect`: extract/verify) and the same mark in 2-D images.
"""

from gsw.mark.detect import Extraction, Verdict, extract, verify
from gsw.mark.embed import EmbedConfig, EmbedResult, embed
from gsw.mark.image import ImageEmbedConfig, ImageEmbedResult, embed_image, embed_images

__all__ = ["EmbedConfig", "EmbedResult", "Extraction", "ImageEmbedConfig", "ImageEmbedResult", "Verdict", "embed",
           "embed_image", "embed_images", "extract", "verify"]
