"""[hdr]: the model may hold radiance above the frame's full scale: renders above 1 decode to radiance above it
(losses.srgb_to_linear_hdr_torch) and the blur term clips after the exposure integral. No loss of its own."""
from __future__ import annotations

from ...errors import ConfigError
from . import Term, register


@register
class HDR(Term):
    table = "hdr"
    builtin = True

    @classmethod
    def build(cls, trainer):
        if not trainer.cfg.hdr:
            return None
        if trainer.data.blur_space != "linear":
            raise ConfigError("[hdr] needs the linear-light blur model (blur.space = \"linear\", or a scene whose "
                              "/train transfer is srgb)")
        return cls(trainer)
