"""ev3dgs.sensor's written-out constants against the reference library they come from."""
import numpy as np

from ev3dgs.sensor import LUMINANCE_WEIGHTS


def test_luminance_weights_are_colour_science_srgb_y_row():
    import colour
    expect = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ[1], dtype=np.float64)
    np.testing.assert_array_equal(LUMINANCE_WEIGHTS, expect)  # the same float64 values, bit for bit
    assert LUMINANCE_WEIGHTS.dtype == np.float64 and LUMINANCE_WEIGHTS.flags.c_contiguous


def test_trainer_import_does_not_pull_in_plotting():
    """`ev3dgs train` processes start without colour-science's plotting (matplotlib) or scipy.spatial."""
    import subprocess
    import sys

    code = ("import sys, ev3dgs.train.trainer, ev3dgs.train.evaluate; "
            "print(','.join(m for m in ('colour', 'matplotlib.pyplot', 'scipy.spatial') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", out
