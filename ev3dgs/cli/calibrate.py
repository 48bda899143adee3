"""`ev3dgs-sim calibrate` (fit the simulator's DVS model to a real recording with APS frames) and
`ev3dgs-sim compare` (re-simulate a recording from its own APS frames and compare with its events)."""
from __future__ import annotations

from .common import add_output_options, finite_float, int_in

MIN_BOOTSTRAP = 3              # resamples: a standard error needs more than two finite ones (calib.thresholds)
MAX_BOOTSTRAP = 10000          # the standard errors settle long before; more only costs time
SEED = int_in(0, 2**32 - 1)     # numpy's seeds


def _calibrate(args) -> int:
    from ..calib.report import calibrate_recording, to_toml
    from ..outputs import atomic_path, check_output_file

    check_output_file(args.out, force=args.force, make_parents=True)   # before reading and fitting
    from ..claims import claim_output
    claim_output(args.out, force=args.force)  # one writer (ev3dgs.claims)
    cal = calibrate_recording(args.input, boot=args.bootstrap, seed=args.seed)
    text = to_toml(cal)
    with atomic_path(args.out) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    if not args.quiet:
        th, nz = cal.thresholds, cal.noise
        print(f"C_on {th.c_on.value:.3f} +- {th.c_on.se:.3f}, C_off {th.c_off.value:.3f} +- {th.c_off.se:.3f}, "
              f"{nz.static_pixels} static pixels, {len(nz.hot)} hot pixels -> {args.out}")
    return 0


def _compare(args) -> int:
    import json

    from ..calib.compare import compare_recording, dark_from_toml, figure, public
    from ..exporters.common import check_out_dir, staged_dir
    from ..sim.config import load_sim_config

    check_out_dir(args.out, args.force)                   # before reading and simulating
    from ..claims import claim_output
    claim_output(args.out, force=args.force, folder=True)
    cfg = load_sim_config(args.config)
    dark = args.aps_dark
    if dark is None:
        dark = (dark_from_toml(args.config, cfg) if args.config else None) or 0.0
    res = compare_recording(args.input, cfg, dark=dark, seed=args.seed)
    res["config"] = args.config or "default"
    with staged_dir(args.out, force=args.force) as stage:
        figure(res, stage / "compare.png", title=f"{res['recording']}: real vs simulated ({res['config']})")
        (stage / "compare.json").write_text(json.dumps(public(res), indent=1) + "\n", encoding="utf-8")
    if not args.quiet:
        cm, bg = res["count_maps"]["all"], res["background"]
        c = cm["corr_pair_pixel"]
        e = bg["rel_error"]
        print(f"{res['real_events']} real, {res['sim_events']} simulated events; count-map correlation "
              f"{'n/a' if c is None else f'{c:.3f}'}, background rate {bg['real_hz']:.3g} Hz real vs "
              f"{bg['sim_hz']:.3g} Hz simulated ({'n/a' if e is None else f'{100 * e:+.0f} %'}) -> {args.out}")
    return 0


def add_calibrate_parsers(sub) -> None:
    """Register `calibrate` and `compare` on an ev3dgs-sim subparsers object."""
    c = sub.add_parser("calibrate", help="fit thresholds, mismatch, noise and refractory period to a recording "
                                         "with APS frames -> a sensor TOML for --config")
    c.add_argument("input", help="recording with APS frames and events (.aedat4, AEDAT 3.1 or 2.0)")
    c.add_argument("--out", required=True, help="output sensor .toml (written atomically)")
    c.add_argument("--bootstrap", type=int_in(MIN_BOOTSTRAP, MAX_BOOTSTRAP), default=200,
                   help=f"bootstrap resamples for the standard errors, {MIN_BOOTSTRAP} to {MAX_BOOTSTRAP} "
                        "(default %(default)s)")
    c.add_argument("--seed", type=SEED, default=0, help="random seed of the bootstrap, >= 0 (default %(default)s)")
    add_output_options(c)
    c.set_defaults(func=_calibrate)
    m = sub.add_parser("compare", help="re-simulate a recording's events from its APS frames and compare them "
                                       "with the real events -> report folder (JSON + figure)")
    m.add_argument("input", help="recording with APS frames and events (.aedat4, AEDAT 3.1 or 2.0)")
    m.add_argument("--config", help="sensor TOML ([dvs] and effect tables), e.g. from `ev3dgs-sim calibrate` "
                                    "(default: none, the built-in DAVIS346-like settings)")
    m.add_argument("--out", required=True, help="output report folder: compare.json and compare.png "
                                                "(written atomically)")
    m.add_argument("--aps-dark", type=finite_float,
                   help="APS dark level in DN subtracted before the simulation (default: the config's "
                        "[aps] dark_dn that calibrate writes, else 0)")
    m.add_argument("--seed", type=SEED, default=0,
                   help="random seed of the simulator's noise, >= 0 (default %(default)s)")
    add_output_options(m)
    m.set_defaults(func=_compare)
