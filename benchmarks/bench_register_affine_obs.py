"""The flag and the textureless rows with the map's local affine bound (session 55).

Runs one of the benches that assess cached fields with ``_confidence.AFFINE_PRIOR`` set, so that
every confidence map the assessment builds (``register()``'s checks, the benches' own maps) takes
the smaller of the window's translation information and its affine marginal
(``_confidence.affine_lmins``; benchmarks/README.md, "Local affine observability (session 55)")::

    python benchmarks/bench_register_affine_obs.py --prior 0.03 phantoms --out out/phantoms --split train
    python benchmarks/bench_register_affine_obs.py --prior 0.03 flag --split train --size 560 --seeds 2 --textureless --skip elastix

``--noise-share map``: the noise's share of the affine moments from the noise map, as before
session 56 (``robust``, the default: ``_confidence.robust_noise_map``). ``--prior``: the prior standard deviation of each element of a window's displacement gradient
(px per px); the rest goes to the bench unchanged. The fields are the cached ones (register them
first with the bench itself), so only the assessment changes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

BENCHES = ("phantoms", "flag", "textureless")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prior", type=float, required=True, help="the gradient's prior standard deviation (px/px)")
    ap.add_argument(
        "--interior-only",
        action="store_true",
        help="the affine map for the interior's observed share alone (_confidence.AFFINE_INTERIOR_ONLY)",
    )
    ap.add_argument(
        "--noise-share",
        choices=("robust", "map"),
        default="robust",
        help="the noise's share in the affine moments from _confidence.robust_noise_map (session 56) or,"
        " as sessions 55's, from the noise map that reads a strong rim as noise",
    )
    ap.add_argument("bench", choices=BENCHES)
    a, rest = ap.parse_known_args(argv)
    if not a.prior > 0:
        ap.error("--prior must be positive")
    from radiokit.register import _confidence as C

    C.AFFINE_PRIOR = a.prior
    C.AFFINE_INTERIOR_ONLY = a.interior_only
    if a.noise_share == "map":
        C.robust_noise_map = C.noise_map  # observability() reads it through the module
    print(
        f"map: local affine bound, prior {a.prior} px/px, interior only: {a.interior_only},"
        f" noise's share: {a.noise_share}",
        flush=True,
    )
    if a.bench == "phantoms":
        from bench_register_phantoms import main as run
    elif a.bench == "flag":
        from bench_register_flag import main as run
    else:
        from bench_register_textureless import main as run
    return run(rest) or 0


if __name__ == "__main__":
    sys.exit(main())
