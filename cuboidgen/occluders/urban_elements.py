"""Urban elements drawn procedurally: the built-in occluders (paper 3.3.1, Figure 15).

The paper cuts trees, cars, pedestrians and signs out of Cityscapes; these are drawn
instead, so no dataset is needed. Each is drawn on a canvas in object coordinates
(x from the object's axis, y up from the ground) and returned tight-cropped, upright,
with its ground contact on the bottom row.
"""
from __future__ import annotations

import cv2
import numpy as np

KINDS = ("tree", "car", "pedestrian", "pole", "sign")


def tight_crop(mask: np.ndarray) -> np.ndarray | None:
    """The foreground's bounding box as a 0/1 uint8 array (the form every occluder mask has);
    None when there is no foreground."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    return np.ascontiguousarray(mask[ys.min():ys.max() + 1, xs.min():xs.max() + 1] != 0, dtype=np.uint8)


def _n(v):
    return max(1, int(round(v)))


class _Canvas:
    """Drawing surface in object coordinates: x from the object's axis, y up from the ground."""

    ROWS, COLS, GROUND = 340, 480, 320  # big enough that no variant is clipped at the edge

    def __init__(self):
        self.img = np.zeros((self.ROWS, self.COLS), np.uint8)

    def _p(self, x, y):
        return int(round(self.COLS / 2 + x)), int(round(self.GROUND - y))

    def poly(self, pts):
        cv2.fillPoly(self.img, [np.array([self._p(x, y) for x, y in pts], np.int32)], 1)

    def circle(self, x, y, r):
        cv2.circle(self.img, self._p(x, y), _n(r), 1, -1)

    def ellipse(self, x, y, rx, ry, angle=0.0, start=0, end=360):
        cv2.ellipse(self.img, self._p(x, y), (_n(rx), _n(ry)), -angle, start, end, 1, -1)

    def rect(self, x0, y0, x1, y1):
        cv2.rectangle(self.img, self._p(x0, y0), self._p(x1, y1), 1, -1)

    def line(self, pts, width):
        for a, b in zip(pts[:-1], pts[1:]):  # thick cv2 lines have round caps: good joints
            cv2.line(self.img, self._p(*a), self._p(*b), 1, _n(width))

    def finish(self, rng, smooth=0.0):
        img = self.img
        if smooth > 0:  # real outlines have no sharp polygon corners
            img = (cv2.GaussianBlur(img.astype(np.float32), (0, 0), smooth) > 0.5).astype(np.uint8)
        img[self.GROUND + 1:] = 0  # nothing below the ground line: contact is the bottom row
        return tight_crop(img[:, ::-1] if rng.random() < 0.5 else img)  # objects face either way


def _cycle(i, options):
    # variants cycle instead of being drawn at random, so even a small library covers all of them
    return options[i % len(options)]


def _foliage(c, rng, cx, cy, rx, ry, n):
    """Overlapping blobs inside an ellipse, then a leafy edge: a smooth crown reads as a balloon."""
    c.ellipse(cx, cy, rx * 0.7, ry * 0.7)
    for _ in range(n):
        r = min(rx, ry) * rng.uniform(0.3, 0.55)
        ang, rad = rng.uniform(0, 2 * np.pi), np.sqrt(rng.uniform(0.2, 1.0))
        c.ellipse(cx + np.cos(ang) * rad * max(rx - r, 0), cy + np.sin(ang) * rad * max(ry - r, 0),
                  r * rng.uniform(0.8, 1.2), r * rng.uniform(0.8, 1.1), rng.uniform(0, 180))
    contours, _ = cv2.findContours(c.img, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    edge = np.concatenate(contours)[:, 0]
    for x, y in edge[rng.integers(0, len(edge), 6 * n)]:  # tufts and gaps centred on the outline
        cv2.circle(c.img, (int(x), int(y)), _n(min(rx, ry) * rng.uniform(0.05, 0.12)), int(rng.random() < .75), -1)


def _tree(rng, h, i):
    c = _Canvas()
    if _cycle(i, "TTTTBTTTTTB") == "B":  # bush or hedge: no trunk, flattened by the ground
        ry = h * rng.uniform(0.22, 0.32)
        _foliage(c, rng, 0, ry * 0.55, ry * rng.uniform(1.3, 2.4), ry, rng.integers(8, 15))
        return c.finish(rng, smooth=1.2)
    th, tw = h * rng.uniform(0.25, 0.45), h * rng.uniform(0.04, 0.08)
    lean = rng.uniform(-0.15, 0.15) * th
    ry = (h - th) * rng.uniform(0.48, 0.55)  # below 0.5 the fork of the limbs shows
    rx, cy = ry * rng.uniform(0.55, 1.35), h - ry
    _foliage(c, rng, lean, cy, rx, ry, rng.integers(7, 15))  # first, so the leafy edge spares the trunk
    c.poly([(-tw * 0.8, 0), (tw * 0.8, 0), (lean + tw * 0.45, th * 1.3), (lean - tw * 0.45, th * 1.3)])
    for _ in range(rng.integers(1, 4)):  # limbs between trunk and crown thin the silhouette there
        tip = (lean + rng.uniform(-0.7, 0.7) * rx, cy - rng.uniform(0.1, 0.5) * ry)
        c.line([(lean * 0.8, th * 0.8), tip], tw * 0.45)
    return c.finish(rng, smooth=1.0)


# kind -> (length range, height/length range, wheel radius/length, axles, side profile as
# (x from the rear, y up) fractions of length and body height)
_VEHICLES = {
    "sedan": ((220, 300), (.3, .35), .075, (.18, .8),
              [(0, 0), (0, .55), (.2, .62), (.3, 1), (.6, 1), (.76, .64), (.97, .56), (1, .35), (1, 0)]),
    "hatch": ((190, 250), (.34, .39), .08, (.17, .81),
              [(0, 0), (0, .6), (.05, .9), (.12, 1), (.55, 1), (.72, .64), (.96, .56), (1, .35), (1, 0)]),
    "suv": ((210, 270), (.37, .43), .085, (.18, .8),
            [(0, 0), (0, .7), (.03, .95), (.08, 1), (.62, 1), (.78, .66), (.97, .6), (1, .4), (1, 0)]),
    "van": ((210, 280), (.4, .5), .07, (.16, .82),
            [(0, 0), (0, .96), (.02, 1), (.74, 1), (.87, .6), (.98, .52), (1, .3), (1, 0)]),
    "bus": ((300, 380), (.27, .32), .055, (.17, .76), [(0, 0), (0, .97), (.02, 1), (.97, 1), (1, .94), (1, 0)]),
}


def _car_side(rng, c, kind):
    (l0, l1), (a0, a1), wr, axles, profile = _VEHICLES[kind]
    length = rng.uniform(l0, l1)
    height, r = length * rng.uniform(a0, a1), length * wr
    base = r * rng.uniform(0.55, 0.8)  # ground clearance: the wheels must show below the body
    c.poly([((fx + rng.uniform(-.015, .015)) * length - length / 2,
             base + (fy + rng.uniform(-.02, .02) * (0 < fy < 1)) * (height - base)) for fx, fy in profile])
    for ax in axles:
        c.circle(ax * length - length / 2, r, r)


def _car_rear(rng, c):
    """Parked cars are often seen end-on: wide body, tapered glasshouse, two tyres."""
    w = rng.uniform(120, 170)
    h = w * rng.uniform(0.72, 0.85)
    c.rect(-w / 2, h * 0.12, w / 2, h * 0.58)
    c.poly([(-w * 0.47, h * 0.55), (w * 0.47, h * 0.55), (w * 0.34, h), (-w * 0.34, h)])
    for s in (-1, 1):
        c.rect(s * w * 0.44, 0, s * w * 0.3, h * 0.2)
        c.rect(s * w * 0.44, h * 0.58, s * w * 0.53, h * 0.66)  # wing mirror


def _car(rng, h, i):
    c = _Canvas()
    kind = _cycle(i, ["sedan", "hatch", "rear", "van", "suv", "sedan", "bus", "hatch", "rear", "suv"])
    if kind == "rear":
        _car_rear(rng, c)
    else:
        _car_side(rng, c, kind)
    return c.finish(rng, smooth=1.8)


def _torso(c, rng, x0, h, sw, side):
    """Head, neck and trunk; a coat or skirt sometimes flares below the hips."""
    hr, lean = h * rng.uniform(.058, .068), h * rng.uniform(0, .03) * side  # walkers lean forward
    c.circle(x0 + lean * 1.5, h - hr, hr)
    c.line([(x0 + lean, h * .8), (x0 + lean * 1.3, h - hr)], hr * 1.1)
    yh = h * rng.uniform(.47, .52)
    hem = yh - (h * rng.uniform(.08, .2) if rng.random() < .3 else 0)
    hip = sw * (.95 if side else .75) / 2 * (1 + (yh - hem) / h * 2.5)
    waist = sw * (.85 if side else .72) / 2
    c.poly([(x0 + lean - sw / 2, h * .8), (x0 + lean + sw / 2, h * .8), (x0 + waist, h * .63),
            (x0 + hip, hem), (x0 - hip, hem), (x0 - waist, h * .63)])
    return yh


def _legs(c, rng, x0, h, yh, sw, side, lt):
    # side view: legs stride front/back; front view: legs nearly parallel, slightly apart
    stride = h * rng.uniform(0, .35) if side else h * rng.uniform(.03, .1)
    for s in (-1, 1):
        foot, hip = x0 + s * stride / 2, x0 if side else x0 + s * sw * .18
        knee = ((hip + foot) / 2 + (h * rng.uniform(0, .03) if side else 0), h * .27)
        c.line([(hip, yh), knee, (foot, lt / 2)], lt)
        c.ellipse(foot + h * .025 * side, h * .015, h * (.05 if side else .03), h * .017)  # shoe
    return stride


def _person(c, rng, x0, h, raise_hand=False):
    """One upright person seen from the side or the front; returns the front hand position."""
    side = int(rng.random() < 0.55)
    sw = h * (rng.uniform(.13, .17) if side else rng.uniform(.22, .27))  # body depth or shoulder width
    lt = h * rng.uniform(.065, .085)
    yh = _torso(c, rng, x0, h, sw, side)
    stride, at, hand = _legs(c, rng, x0, h, yh, sw, side, lt), lt * .75, None
    for s in (-1, 1):
        sh = (x0 + (0 if side else s * (sw / 2 - at / 3)), h * .8 - at / 2)
        c.circle(sh[0], sh[1], at * .6)
        if raise_hand and s == 1:
            hand, elbow = (x0 + sw * .45, h * .72), (x0 + sw * .6 + h * .04, h * .6)
        elif side:  # arms swing against the legs
            hand = (x0 - s * stride * rng.uniform(.3, .6), h * rng.uniform(.44, .5))
            elbow = ((sh[0] + hand[0]) / 2, h * .62)
        else:
            hand = (x0 + s * (sw / 2 + h * rng.uniform(0, .04)), h * rng.uniform(.44, .5))
            elbow = (x0 + s * (sw / 2 + h * .01), h * .62)
        c.line([sh, elbow, hand], at)
    return hand


def _pedestrian(rng, h, i):
    c = _Canvas()
    variant = _cycle(i, ["single", "pair", "bag", "single", "umbrella", "single", "pair", "bag"])
    if variant == "pair":  # people walking together merge into one silhouette
        gap = h * rng.uniform(0.12, 0.26)
        _person(c, rng, -gap, h)
        _person(c, rng, gap, h * rng.uniform(0.6, 1.05))
    elif variant == "umbrella":
        hx, hy = _person(c, rng, 0, h, raise_hand=True)
        top = h * rng.uniform(1.08, 1.16)
        c.line([(hx, hy), (hx, top)], h * 0.015)
        c.ellipse(hx, top - h * 0.1, h * rng.uniform(0.32, 0.42), h * 0.12, 0, 180, 360)
    else:
        hx, hy = _person(c, rng, 0, h)
        if variant == "bag":
            bw, bh = h * rng.uniform(0.09, 0.16), h * rng.uniform(0.1, 0.17)
            c.line([(hx, hy), (hx, hy - h * 0.03)], h * 0.012)
            c.rect(hx - bw / 2, hy - h * 0.03, hx + bw / 2, hy - h * 0.03 - bh)
    return c.finish(rng, smooth=0.8)


def _post(c, h, w):
    c.poly([(-w * 0.7, 0), (w * 0.7, 0), (w * 0.5, h), (-w * 0.5, h)])  # slight taper
    c.rect(-w * 1.1, 0, w * 1.1, h * 0.04)  # foot plinth


def _pole(rng, h, i):
    c = _Canvas()
    w = h * rng.uniform(0.025, 0.045)
    kind = _cycle(i, ["lamp", "traffic light", "bare", "lamp", "double lamp", "traffic light", "bollard"])
    if kind == "bollard":
        bh = h * rng.uniform(0.35, 0.5)
        bw = bh / rng.uniform(3.5, 5)
        c.rect(-bw / 2, 0, bw / 2, bh - bw / 2)
        c.circle(0, bh - bw / 2, bw / 2)
    elif kind == "traffic light":
        _post(c, h * 0.8, w)
        bw, bh = h * rng.uniform(0.07, 0.09), h * rng.uniform(0.2, 0.26)
        c.rect(-bw / 2, h - bh, bw / 2, h)
        for y in h - bh * (np.arange(3) + 0.3) / 3:  # sun visors over the three lamps
            c.poly([(bw / 2, y), (bw * 0.9, y - bh * 0.03), (bw / 2, y - bh * 0.08)])
    else:  # mast, optionally with outreach arms and flat luminaires
        _post(c, h * (1.0 if kind == "bare" else 0.95), w)
        arm = h * rng.uniform(0.1, 0.2)
        for s in {"lamp": (1,), "double lamp": (-1, 1), "bare": ()}[kind]:
            c.line([(0, h * 0.95), (s * arm * 0.3, h), (s * arm, h * 0.98)], w * 0.6)
            c.ellipse(s * arm, h * 0.965, h * rng.uniform(0.04, 0.07), h * 0.02)
    return c.finish(rng, smooth=0.6)


def _plate(c, rng, cy, s, shape):
    if shape == "rect":
        w, hh = s * rng.uniform(0.8, 1.5), s * rng.uniform(0.6, 1.2)
        c.rect(-w / 2, cy - hh / 2, w / 2, cy + hh / 2)
    elif shape == "circle":
        c.circle(0, cy, s / 2)
    elif shape == "triangle":  # warning sign points up, give-way sign points down
        d = 1 if rng.random() < 0.6 else -1
        c.poly([(-s / 2, cy - d * s * 0.29), (s / 2, cy - d * s * 0.29), (0, cy + d * s * 0.58)])
    else:
        ang = np.pi / 8 + np.arange(8) * np.pi / 4
        c.poly(list(zip(np.cos(ang) * s / 2, cy + np.sin(ang) * s / 2)))


def _sign(rng, h, i):
    c = _Canvas()
    s = h * rng.uniform(0.2, 0.32)
    if _cycle(i, "PPPPPPPB") == "B":  # direction board on two posts
        w = s * rng.uniform(1.8, 2.6)
        for x in (-w * 0.32, w * 0.32):
            c.rect(x - h * 0.015, 0, x + h * 0.015, h - s / 2)
        c.rect(-w / 2, h - s * 0.8, w / 2, h)
        return c.finish(rng)
    _post(c, h - s / 2, h * rng.uniform(0.025, 0.04))
    _plate(c, rng, h - s / 2, s, _cycle(i, ["circle", "triangle", "rect", "octagon", "rect", "circle"]))
    if rng.random() < 0.35:  # supplementary panel under the main plate
        pw = s * rng.uniform(0.7, 1.0)
        c.rect(-pw / 2, h - s * 1.1, pw / 2, h - s * 1.1 - s * rng.uniform(0.25, 0.4))
    return c.finish(rng, smooth=0.5)


_DRAW = {"tree": _tree, "car": _car, "pedestrian": _pedestrian, "pole": _pole, "sign": _sign}


def draw_element(kind: str, rng: np.random.Generator, height: float, variant: int) -> np.ndarray:
    """One urban element of `kind` (one of KINDS), about `height` px tall, as a tight-cropped
    upright 0/1 mask; `variant` cycles through the kind's sub-types (sedan, van, bus, ...)."""
    return _DRAW[kind](rng, height, variant)
