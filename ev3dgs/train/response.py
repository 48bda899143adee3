"""--learn-response: a learned monotone camera response in front of the scene's sRGB decode.

A camera's frames are rarely plain sRGB: a tone curve (contrast, shoulder, a gamma other than 2.4) sits between
the light the sensor integrates and the display values written to the file. The blur model averages the
sub-poses in linear light and the events see log linear light, so a wrong decode makes the two disagree; the
frame's own PSNR does not see it (a sharp frame's decode and encode cancel). This module learns the part the
scene's declared transfer misses, as DiET-GS learns a camera response next to its event double integral:

    linear = srgb_decode(h(d)),    blurry frame = h^-1(srgb_encode(mean of linear over the sub-poses))

where d is the rendered display value (what the frames and the evaluation compare) and h is a monotone
piecewise-linear map of [0, 1] onto itself with ``knots`` equal segments. Its segment heights are a softmax of free
logits, so h is strictly increasing with h(0) = 0 and h(1) = 1 for any logits, and logits of 0 give the identity,
bit for bit on [0, 1] and below (every height 1/knots, a power of two for the default 16): a run with the response
learned starts where the fixed decode is. Outside [0, 1] (renders below black, and above full scale with --hdr) h
continues with its end segments' slopes. Both h and its inverse are exact (no iteration), and deterministic.
"""
from __future__ import annotations

import torch

DEFAULT_KNOTS = 16
RESPONSE_LR = 5e-3  # Adam, on the logits: a height can change by a factor of e in about 200 steps


class ResponseCurve:
    """The learned map h (module docstring). ``logits``: (knots,) float tensor, the only parameter."""

    def __init__(self, knots: int = DEFAULT_KNOTS, device="cpu", dtype=torch.float32):
        if knots < 1:
            raise ValueError(f"knots must be >= 1, got {knots}")
        self.logits = torch.zeros(knots, device=device, dtype=dtype, requires_grad=True)

    @property
    def knots(self) -> int:
        return int(self.logits.shape[0])

    def heights(self) -> torch.Tensor:
        """(knots,) segment heights: positive, summing to 1."""
        return torch.softmax(self.logits, dim=0)

    def values(self) -> torch.Tensor:
        """(knots + 1,) h at the knots 0, 1/knots, ..., 1 (the last is 1 up to the softmax's rounding)."""
        hts = self.heights()
        return torch.cat([torch.zeros(1, dtype=hts.dtype, device=hts.device), torch.cumsum(hts, 0)])

    def __call__(self, d: torch.Tensor) -> torch.Tensor:
        """h(d), elementwise, any shape."""
        n = self.knots
        hts, y = self.heights(), self.values()
        u = d * n                                              # knot units
        idx = torch.clamp(torch.floor(u), 0, n - 1).long()     # the segment (end segments extend outwards)
        return y[idx] + (u - idx.to(u.dtype)) * hts[idx]

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        """h^-1(z), elementwise: the segment whose values bracket z, then the line through it."""
        n = self.knots
        hts, y = self.heights(), self.values()
        # the first knot value above z, among the inner knots: 0..n-1 (below 0 -> 0, above the last -> n-1)
        idx = torch.bucketize(z.detach().contiguous(), y[1:n].detach().contiguous(), right=True)
        return (idx.to(z.dtype) + (z - y[idx]) / hts[idx]) / n

    def state_dict(self) -> dict:
        return {"logits": self.logits.detach().clone()}

    def load_state_dict(self, state: dict) -> None:
        logits = state["logits"]
        if tuple(logits.shape) != tuple(self.logits.shape):
            raise ValueError(f"response: {tuple(logits.shape)} logits, expected {tuple(self.logits.shape)}")
        with torch.no_grad():
            self.logits.copy_(logits)

    def table(self) -> dict:
        """The curve as a user reads it: display value in -> the value the sRGB decode then sees."""
        n = self.knots
        return {"display": [i / n for i in range(n + 1)],
                "decoded_as": [float(v) for v in self.values().detach().cpu().double()]}
