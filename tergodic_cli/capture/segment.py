"""Target segmentation by colour, in HSV with tolerances.

A target spec is a named colour (``red``, ``green``, ``blue``, ``yellow``,
``orange``, ``magenta``, ``cyan``, ``black``, ``white``), ``all`` for uniform
coverage, or an explicit range ``hsv:H1-H2,SMIN,VMIN`` (hue in degrees, wrapping
when H1 > H2; saturation and value in [0, 1]).

The target weight of a colour (:func:`target_weight`) is continuous: 1 inside the HSV box, and for
a colour of the box's hue but paler than SMIN (partly wiped ink blended with the surface), the
saturation ramp (s - FAINT_S) / (SMIN - FAINT_S), so faint ink still draws the agent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tergodic_cli.errors import TergodicError, require


@dataclass(frozen=True)
class HsvRange:
    """An HSV box: hue interval in degrees (may wrap through 0; 0..360 is any hue), lower/upper s and v bounds."""

    hue_lo: float
    hue_hi: float
    s_min: float = 0.0
    s_max: float = 1.0
    v_min: float = 0.0
    v_max: float = 1.0

    def contains(self, hsv: np.ndarray) -> np.ndarray:
        """Which colours are in the range.

        Parameters
        ----------
        hsv : (n, 3) float
            Hue in degrees [0, 360), saturation and value in [0, 1].

        Returns
        -------
        (n,) bool
        """
        h, s, v = hsv.T
        if self.hue_lo <= self.hue_hi:
            hue_ok = (h >= self.hue_lo) & (h <= self.hue_hi)
        else:  # wraps through 0/360, e.g. red
            hue_ok = (h >= self.hue_lo) | (h <= self.hue_hi)
        return hue_ok & (s >= self.s_min) & (s <= self.s_max) & (v >= self.v_min) & (v <= self.v_max)

    def weight(self, hsv: np.ndarray) -> np.ndarray:
        """Continuous target weight: 1 inside the box, the saturation ramp below SMIN (module doc).

        Parameters
        ----------
        hsv : (n, 3) float
            Hue (degrees), saturation and value in [0, 1].

        Returns
        -------
        (n,) float in [0, 1]
        """
        inside = self.contains(hsv)
        if self.s_min <= FAINT_S:  # no saturation to ramp on (black, white, grey ranges)
            return inside.astype(np.float64)
        pale = HsvRange(self.hue_lo, self.hue_hi, FAINT_S, self.s_min, self.v_min, self.v_max).contains(hsv)
        ramp = np.clip((hsv[:, 1] - FAINT_S) / (self.s_min - FAINT_S), 0.0, 1.0)
        return np.where(inside, 1.0, np.where(pale, ramp, 0.0))


#: Saturation at and below which a colour carries no ink: above a plain surface's (glazed ceramic
#: 0.07, white 0) and its 8-bit shading noise. Red ink blended to m with the glaze weighs in from
#: m ~ 0.08, where its hue enters the red band (docs/sim_camera.md).
FAINT_S = 0.1
_CHROMATIC = {"red": 0.0, "orange": 30.0, "yellow": 60.0, "green": 120.0, "cyan": 180.0, "blue": 240.0, "magenta": 300.0}
HUE_TOLERANCE_DEG = 20.0
NAMED = {name: HsvRange((c - HUE_TOLERANCE_DEG) % 360.0, (c + HUE_TOLERANCE_DEG) % 360.0, s_min=0.5, v_min=0.25)
         for name, c in _CHROMATIC.items()}
NAMED["black"] = HsvRange(0.0, 360.0, v_max=0.2)
NAMED["white"] = HsvRange(0.0, 360.0, s_max=0.2, v_min=0.8)


def parse_target(spec: str) -> HsvRange | None:
    """Parse a ``--target`` spec.

    Parameters
    ----------
    spec : str
        A colour name, ``hsv:H1-H2,SMIN,VMIN`` or ``all``.

    Returns
    -------
    HsvRange or None
        None means ``all`` (uniform target).
    """
    spec = spec.strip().lower()
    if spec == "all":
        return None
    if spec in NAMED:
        return NAMED[spec]
    if spec.startswith("hsv:"):
        try:
            hue, s_min, v_min = spec[4:].split(",")
            lo, hi = (float(x) for x in hue.split("-"))
            s_lo, v_lo = float(s_min), float(v_min)
        except ValueError:
            raise TergodicError(f"bad HSV target '{spec}'", "write it as hsv:H1-H2,SMIN,VMIN, e.g. hsv:340-20,0.5,0.3") from None
        # Checked here: a hue of 400 would wrap silently and end as "no points match".
        if not (0.0 <= lo <= 360.0 and 0.0 <= hi <= 360.0):
            raise TergodicError(f"hue {lo if not 0.0 <= lo <= 360.0 else hi:g} in --target '{spec}' is outside 0..360 degrees",
                                "e.g. hsv:340-20,0.5,0.3 (hues wrap through 0 when H1 > H2)")
        if not (0.0 <= s_lo <= 1.0 and 0.0 <= v_lo <= 1.0):
            raise TergodicError(f"SMIN and VMIN in --target '{spec}' must be within 0..1", "e.g. hsv:340-20,0.5,0.3")
        return HsvRange(lo % 360.0, hi % 360.0, s_min=s_lo, v_min=v_lo)
    raise TergodicError(
        f"unknown target colour '{spec}'",
        f"use one of {', '.join(sorted(NAMED))}, 'all', or hsv:H1-H2,SMIN,VMIN",
    )


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """Vectorised RGB -> HSV.

    Parameters
    ----------
    rgb : (n, 3) float
        In [0, 1].

    Returns
    -------
    (n, 3) float
        Hue in degrees [0, 360), saturation and value in [0, 1].
    """
    r, g, b = rgb.T
    cmax, delta = rgb.max(axis=1), np.ptp(rgb, axis=1)
    d = np.where(delta > 0, delta, 1.0)  # grey (delta 0) has hue 0
    hue = np.select([delta == 0, cmax == r, cmax == g], [0.0, ((g - b) / d) % 6.0, (b - r) / d + 2.0],
                    (r - g) / d + 4.0).astype(np.float64)
    sat = np.where(cmax > 0, delta / np.where(cmax > 0, cmax, 1.0), 0.0)
    return np.column_stack([hue * 60.0, sat, cmax])


def target_weight(colors: np.ndarray | None, target: HsvRange | None, n: int) -> np.ndarray:
    """Target weight in [0, 1] of each colour: 1 on the marking, a ramp on faint ink, 0 elsewhere.

    A saturated marking on a plain surface gets a binary mask (the pipeline's ``weight >= 1``).

    Parameters
    ----------
    colors : (n, 3) float or None
        RGB in [0, 1].
    target : HsvRange or None
        None (``all``): every point weighs 1.
    n : int
        Number of points.

    Returns
    -------
    (n,) float
    """
    if target is None:
        return np.ones(n)
    require(colors is not None, "the cloud has no colours, so no target can be segmented",
            "give a coloured cloud, or pass --target all for uniform coverage")
    return target.weight(rgb_to_hsv(colors))
