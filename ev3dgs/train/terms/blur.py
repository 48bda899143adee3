"""[blur]: the blur rendering loss. The mean of the view's b+1 sub-pose renders, averaged in the scene's blur
space (decoded to linear light where the [hdr] or [response] terms or the events need it), against the
blurry frame: (1 - lambda) MSE + lambda (1 - SSIM). Always on (naive: one render at the mid pose; oracle: the
sharp frame at its pose). Publishes for later terms: ``linear`` (the decoded renders or None) and ``average``."""
from __future__ import annotations

from ..losses import average_loss, blur_average, srgb_to_linear_hdr_torch, srgb_to_linear_torch
from ..metrics import psnr_later
from . import Term, register


@register
class Blur(Term):
    table = "blur"
    builtin = True

    @classmethod
    def build(cls, trainer):
        return cls(trainer)

    def cameras(self, step):
        return step.poses

    def loss(self, step):
        cfg, data = self.trainer.cfg, self.trainer.data
        stack = step.images(self)
        response, hdr = self.trainer.term("response"), self.trainer.term("hdr") is not None
        # both losses decode the renders to linear light (blur average in linear light, events from linear
        # intensity): decode once, so the decode and its backward run once per step. [hdr]: renders above 1
        # decode to radiance above full scale, and the sensor's clip follows the exposure integral
        shown = stack if response is None else response.curve(stack)   # [response]: h(render)
        if hdr:
            lin = srgb_to_linear_hdr_torch(shown)
        else:
            wants = any(getattr(t, "wants_linear", False) for t in self.trainer.terms)
            lin = (srgb_to_linear_torch(shown) if response is not None or (
                wants and data.blur_space == "linear" and data.event_transfer == "srgb") else None)
        avg = blur_average(stack, data.blur_space, linear=lin)  # data.blur_space: "auto" resolved from the scene
        if response is not None:  # back through h^-1 to the frame's display values
            avg = response.curve.inverse(avg)
        step.shared["linear"], step.shared["average"] = lin, avg
        l_blur = average_loss(avg, step.target, cfg.ssim_lambda, clip=hdr)
        return l_blur, {"blur": l_blur.detach()}   # read back with the step's record (readback.py)

    def after_step(self, step):
        # the blurry frame as the loss saw it (averaged in data.blur_space); its PSNR computed when read back
        out = {"psnr_blurry": psnr_later(step.shared["average"].detach().clamp(0, 1), step.target)}
        if self.trainer.data.n_sub is not None:
            out["subposes"] = step.k
        return out
