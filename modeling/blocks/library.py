"""The library of 3D blocks (the DEM-blocks paper, section 3.1): roof forms with their
parameters, variants, and the surface S_x of a block on its support.

Every roof of the library is the minimum of affine functions of the block's own frame
(s along the ridge, t across it, both metres from the support's corner): a gable is the
lower of two planes rising from the eaves, a hip adds a plane rising from each free end,
a mansard a steep and a shallow plane per side; the semi-elliptic vault is the lower of
the chords of its ellipse (the piecewise-linear roof its mesh has). So one formula gives
the height at a cell, and the faces of the mesh are convex polygons
(:mod:`.block_meshes`).

A block's variant is its orientation on the support (the ridge along the support's u or
v axis; for a shed, which side is low) and its ends: an end of the ridge that is a common
edge with a neighbouring support is a junction ("-", "L", "T" or "+" by how many of its
ends are) and gets no end plane, the roof running on into the neighbour; a free end is
straight (gable) or hipped by the form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: form name: (the paper's family, parameter names). Heights are absolute metres;
#: ``hip`` and ``inset`` are metres along the ridge and across it.
FORMS: dict[str, tuple[str, tuple[str, ...]]] = {
    "flat": ("monoplane", ("h_gutter",)),
    "shed": ("monoplane", ("h_gutter", "h_top")),
    "gable": ("multiplane", ("h_gutter", "h_top")),
    "hipped": ("multiplane", ("h_gutter", "h_top", "hip")),
    "half-hipped": ("multiplane", ("h_gutter", "h_top", "h_hip", "hip")),
    "pyramid": ("multiplane", ("h_gutter", "h_top")),
    "mansard": ("multiplane", ("h_gutter", "h_break", "h_top", "inset")),
    "gambrel": ("multiplane", ("h_gutter", "h_break", "h_top", "inset")),
    "semi-elliptic": ("curved", ("h_gutter", "h_top")),
}
#: forms whose roof does not depend on the ridge's direction on a square support
_ORIENTATION_FREE = ("flat", "pyramid")
#: forms with a ridge that a junction can carry on into the neighbour
RIDGED = ("shed", "gable", "hipped", "half-hipped", "mansard", "gambrel", "semi-elliptic")
_ARC_CHORDS = 8  # chords of the semi-elliptic vault (its mesh and its surface)
_MIN_LENGTH = 0.5  # metres: the shortest hip or inset
#: metres: the least rise of a pitched roof (and between its gutter, break or hip height
#: and its top): a gable of no rise is a flat roof, which the library has; the paper does
#: not allow such degenerate blocks
MIN_RISE = 0.5


@dataclass(frozen=True)
class Frame:
    """A support's frame: u along ``theta`` (radians from east), v to its left, both
    metres from ``origin`` (world metres); the support lies in [u0, u1] x [v0, v1]."""

    theta: float
    origin: tuple[float, float]
    rect: tuple[float, float, float, float]

    def to_frame(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.theta), np.sin(self.theta)
        dx, dy = x - self.origin[0], y - self.origin[1]
        return c * dx + s * dy, -s * dx + c * dy

    def to_world(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.theta), np.sin(self.theta)
        return self.origin[0] + c * u - s * v, self.origin[1] + s * u + c * v

    def axis(self, along: int) -> np.ndarray:
        """(2,) world unit vector of the frame's u (along 0) or v (along 1) axis."""
        c, s = np.cos(self.theta), np.sin(self.theta)
        return np.array([c, s]) if along == 0 else np.array([-s, c])


@dataclass(frozen=True)
class Block:
    """A 3D block x_i = (m_i, theta_i): a roof form, its variant and its parameters.

    Attributes
    ----------
    form : str
        A key of :data:`FORMS`.
    along : int
        0: the ridge runs along the support's u axis; 1: along v.
    flip : bool
        A shed's low side at the far side of t (ignored by the other forms).
    params : tuple of float
        The form's parameters, in the order of :data:`FORMS`.
    """

    form: str
    along: int
    flip: bool
    params: tuple[float, ...]

    @property
    def gutter(self) -> float:
        return self.params[0]

    @property
    def top(self) -> float:
        names = FORMS[self.form][1]
        return self.params[names.index("h_top")] if "h_top" in names else self.params[0]

    def record(self) -> dict:
        names = FORMS[self.form][1]
        return {
            "form": self.form,
            "family": FORMS[self.form][0],
            "ridge_along": "uv"[self.along],
            **({"low_side": "far" if self.flip else "near"} if self.form == "shed" else {}),
            "params": {n: round(float(p), 3) for n, p in zip(names, self.params, strict=True)},
        }


def ridge_frame(frame: Frame, along: int, ends: tuple[bool, bool, bool, bool]):
    """The block's own extents: length L along the ridge, width W across it, and which
    of the ridge's two ends are junctions. ``ends``: junction on the support's sides
    u0, v0, u1, v1."""
    u0, u1, v0, v1 = frame.rect
    if along == 0:
        return u1 - u0, v1 - v0, (ends[0], ends[2])
    return v1 - v0, u1 - u0, (ends[1], ends[3])


def block_planes(block: Block, L: float, W: float, joined: tuple[bool, bool]) -> np.ndarray:
    """(P, 3) the affine functions z = a s + b t + c whose minimum is the block's roof,
    in its own frame (s in [0, L] along the ridge, t in [0, W] across it, metres).

    joined : whether the ridge's ends at s = 0 and s = L are junctions (no end plane)."""
    p = block.params
    h = p[0]
    planes: list[tuple[float, float, float]] = []

    def sides(k: float, z0: float, offset: float = 0.0) -> None:
        # planes rising with slope k from both eaves, at height z0 at distance offset
        planes.append((0.0, k, z0 - k * offset))
        planes.append((0.0, -k, z0 + k * (W - offset)))

    def ends(k: float, z0: float, offset: float = 0.0) -> None:
        if not joined[0]:
            planes.append((k, 0.0, z0 - k * offset))
        if not joined[1]:
            planes.append((-k, 0.0, z0 + k * (L - offset)))

    half = 0.5 * W
    if block.form == "flat":
        planes.append((0.0, 0.0, h))
    elif block.form == "shed":
        k = (p[1] - h) / max(W, 1e-6)
        planes.append((0.0, -k, h + k * W) if block.flip else (0.0, k, h))
    elif block.form in ("gable", "hipped", "half-hipped"):
        top = p[1]
        sides((top - h) / half, h)
        if block.form == "hipped":
            ends((top - h) / max(p[2], _MIN_LENGTH), h)
        elif block.form == "half-hipped":
            ends((top - p[2]) / max(p[3], _MIN_LENGTH), p[2])
    elif block.form == "pyramid":
        top = p[1]
        sides((top - h) / half, h)
        k = (top - h) / max(0.5 * L, 1e-6)
        planes += [(k, 0.0, h), (-k, 0.0, h + k * L)]
    elif block.form in ("mansard", "gambrel"):
        brk, top, inset = p[1], p[2], max(p[3], _MIN_LENGTH)
        steep = (brk - h) / inset
        shallow = (top - brk) / max(half - inset, _MIN_LENGTH)
        sides(steep, h)
        sides(shallow, brk, inset)
        if block.form == "mansard":
            ends(steep, h)
            ends(shallow, brk, inset)
        planes.append((0.0, 0.0, top))  # the upper slopes meet at h_top
    elif block.form == "semi-elliptic":
        phi = np.linspace(0.0, np.pi, _ARC_CHORDS + 1)
        t = half * (1.0 - np.cos(phi))
        z = h + (p[1] - h) * np.sin(phi)
        for i in range(_ARC_CHORDS):
            k = (z[i + 1] - z[i]) / (t[i + 1] - t[i])
            planes.append((0.0, k, z[i] - k * t[i]))
    else:
        raise ValueError(f"unknown roof form {block.form!r}")
    return np.asarray(planes, np.float64)


def local_coordinates(u: np.ndarray, v: np.ndarray, frame: Frame, along: int):
    """(s, t) of support-frame points (u, v): s along the ridge, t across, from the
    support's corner."""
    u0, _, v0, _ = frame.rect
    return (u - u0, v - v0) if along == 0 else (v - v0, u - u0)


def block_heights(
    block: Block, u: np.ndarray, v: np.ndarray, frame: Frame, ends: tuple[bool, ...]
) -> np.ndarray:
    """S_x: the block's roof height (metres) at support-frame points (u, v), (n,) each."""
    L, W, joined = ridge_frame(frame, block.along, ends)
    planes = block_planes(block, L, W, joined)
    s, t = local_coordinates(u, v, frame, block.along)
    return (planes[:, :1] * s + planes[:, 1:2] * t + planes[:, 2:]).min(axis=0)


def parameter_ranges(form: str, L: float, W: float, z_lo: float, z_hi: float) -> np.ndarray:
    """(k, 2) the range of each of the form's parameters on a support of ridge length L
    and width W (metres) whose heights lie in [z_lo, z_hi]: the domain of the uniform
    kernel and the prior's D_max."""
    z = (z_lo, z_hi)
    out = {
        "h_gutter": z, "h_top": z, "h_hip": z, "h_break": z,
        # a hip end at most twice as steep as the sides: a shorter one is a gable end
        # that the walls' blur shaved, not a hip
        "hip": (max(0.25 * W, _MIN_LENGTH), max(0.5 * L, 0.25 * W, _MIN_LENGTH)),
        "inset": (_MIN_LENGTH, max(0.5 * W - _MIN_LENGTH, _MIN_LENGTH)),
    }  # fmt: skip
    return np.array([out[n] for n in FORMS[form][1]], np.float64)


def valid_params(form: str, params: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """The parameters clipped to their ranges and ordered as the form needs: a pitched
    roof's top at least :data:`MIN_RISE` above its gutter; a half-hip's height that far
    from both; a mansard's break that far above the gutter and at least its inset (a
    lower slope of 45 degrees or more), and not above the top."""
    p = np.clip(params, ranges[:, 0], ranges[:, 1])
    names = FORMS[form][1]
    if "h_top" in names:
        top = names.index("h_top")
        mid = names.index("h_hip") if "h_hip" in names else None
        brk = names.index("h_break") if "h_break" in names else None
        rise = 2 * MIN_RISE if mid is not None or brk is not None else MIN_RISE
        p[top] = max(p[top], p[0] + rise)
        if mid is not None:
            p[mid] = min(max(p[mid], p[0] + MIN_RISE), p[top] - MIN_RISE)
        if brk is not None:  # a mansard's lower slope is steeper than 45 degrees: a
            # gentler one is a hipped roof's, and its break does not show
            inset = p[names.index("inset")]
            p[top] = max(p[top], p[0] + max(MIN_RISE, inset))
            p[brk] = min(max(p[brk], p[0] + max(MIN_RISE, inset)), p[top])
    return p


def orientation_free(form: str) -> bool:
    return form in _ORIENTATION_FREE
