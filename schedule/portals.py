"""Virtual portals (paper §4.2, §6.2, §7.3.3): a 4D max-radiance cache on the 6 faces of every
domain box, recorded in one frame and used to predict the radiance of rays in later ones.

Layout. ``values[d, face, i, j, angle]``, shape (D, 6, R, R, 8) float32 (R = 32 by default),
with a ``recorded`` bool mask of the same shape.

* ``face``: the box face the ray leaves through, ordered (-x, +x, -y, +y, -z, +z): the axis
  of the smallest slab exit distance, and the sign of the direction along it.
* ``i, j``: the exit point's cell on that face. The face's (u, v) axes are the two other box
  axes in cyclic order (x: (y, z), y: (z, x), z: (x, y)), the same for both faces of an axis;
  u and v are normalised over the face rectangle, ``i = clamp(floor(R u), 0, R - 1)`` and
  likewise j.
* ``angle = 4 * cos_bin + phi_bin``: the direction in the outgoing hemisphere. ``cos_bin`` is
  1 when cos(theta) = direction . outward normal >= 0.5 (the upper bin, around the normal),
  else 0; ``phi_bin`` is the quadrant of phi = atan2(direction . t_v, direction . t_u) with
  t_u, t_v the unit (u, v) axes: 0 for [0, pi/2), 1 for [pi/2, pi), 2 for [-pi, -pi/2), 3 for
  [-pi/2, 0) (a direction along the normal has phi = 0). Since solid angle is
  d(cos theta) d(phi), the 8 bins cover equal solid angles (pi / 4 sr each).

Recording keeps the maximum per cell (``np.maximum.at``: "we only keep the maximum radiance");
nodes merge portals element-wise by MAX (values) and OR (mask), which does not depend on the
order, so P nodes record what one process does. A cell never recorded predicts +inf:
conservative, the ray is traced on the fine model.

Prediction accuracy (notes S9, "ACC (reading)"): :class:`CrossingLog` keeps, per path, the
cell where an instrumented recording frame's depth-1 ray crossed its portal and the radiance
it actually brought back (the value recording keeps: the largest ``k c / beta`` of its lit
shadow rays, 0 for a miss or a shadowed hit); :func:`prediction_accuracy` classifies those
crossings with the portals of an earlier frame: ACC is the share whose predicted class
(<= threshold / > threshold) is the actual one, Simple/total the share predicted low.

Memory: D x 6 x R^2 x 8 cells, 4 bytes each for ``values`` (D x 196,608 B at R = 32, 25.2 MB
at D = 128) plus 1 byte each for the bool ``recorded`` mask (D x 49,152 B); :meth:`nbytes`
counts both. :meth:`to_arrays` sends the mask packed to 1 bit per cell (D x 6,144 B).

Pure numpy; no I/O, no asyncio.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Face order: face index = 2 * axis + (direction along the axis > 0).
FACES = ("-x", "+x", "-y", "+y", "-z", "+z")
#: Angular bins per cell: 2 cos(theta) bins x 4 phi quadrants.
ANGLES = 8
#: cos(theta) at which the two cos bins split (equal solid angle).
COS_SPLIT = 0.5
DEFAULT_RESOLUTION = 32
#: The finest portals ``--portal-resolution`` takes (the paper's Table 4 goes up to 128).
MAX_RESOLUTION = 128
#: Rec. 709 / sRGB luminance weights.
LUMINANCE = (0.2126, 0.7152, 0.0722)


#: Most bytes of portals a node may hold: they travel in one tree-reduce message (values and
#: recorded flags), which the codec caps at 1 GiB; half of it leaves room for the rest.
MAX_PORTAL_BYTES = 512 << 20


def records_portals(frame: int, interval: int, have_portals: bool) -> bool:
    """Whether animation frame ``frame`` records portals (every ``interval``-th frame, and any
    frame while none are recorded yet); the frames between predict with the last recorded."""
    return frame % interval == 0 or not have_portals


def portal_bytes(n_domains: int, resolution: int) -> int:
    """Bytes of a node's portals: float32 values and a bool recorded flag per cell."""
    return int(n_domains) * len(FACES) * int(resolution) ** 2 * ANGLES * 5


def check_portal_size(n_domains: int, resolution: int) -> None:
    """Refuse portals too large to merge over the nodes, saying what to do (ValueError)."""
    size = portal_bytes(n_domains, resolution)
    if size > MAX_PORTAL_BYTES:
        fits = int((MAX_PORTAL_BYTES / portal_bytes(n_domains, 1)) ** 0.5)
        raise ValueError(f"--portal-resolution {resolution} needs {size / 2**20:,.0f} MiB of "
                         f"portals on every node for {n_domains} domains, more than the "
                         f"{MAX_PORTAL_BYTES >> 20} MiB one tree-reduce message carries; use "
                         f"--portal-resolution {max(fits, 1)} or less")


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Y = 0.2126 R + 0.7152 G + 0.0722 B of linear RGB.

    Parameters
    ----------
    rgb : (n, 3) linear RGB (any float dtype; integers become float64).

    Returns
    -------
    (n,) luminance in the input's float dtype.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise ValueError(f"expected (n, 3) RGB, got shape {rgb.shape}")
    dtype = rgb.dtype if np.issubdtype(rgb.dtype, np.floating) else np.float64
    return rgb.astype(dtype, copy=False) @ np.asarray(LUMINANCE, dtype=dtype)


class Portals:
    """The virtual portals of D domain boxes.

    Parameters
    ----------
    n_domains : D.
    resolution : R, spatial cells per face edge.

    Attributes
    ----------
    values : (D, 6, R, R, 8) float32, the largest radiance recorded per cell (0 where none).
    recorded : (D, 6, R, R, 8) bool, whether anything was recorded in the cell.
    age : (D, 6, R, R, 8) uint16, frames since the cell was last recorded (``refresh``; local
        to a node, not all-reduced: every node folds in the same merged frames).
    """

    #: Names and combiners (``transport.tree.COMBINE``) of :meth:`to_arrays`' arrays, for an
    #: all-reduce: ``allreduce(portals.to_arrays(), Portals.REDUCE)``.
    REDUCE = {"portal_values": "max", "portal_recorded": "or"}

    def __init__(self, n_domains: int, resolution: int = DEFAULT_RESOLUTION):
        if int(n_domains) < 0 or int(resolution) < 1:
            raise ValueError(f"need n_domains >= 0 and resolution >= 1, got {n_domains}, "
                             f"{resolution}")
        self.resolution = int(resolution)
        self.values = np.zeros(self.shape_for(int(n_domains), self.resolution), np.float32)
        self.recorded = np.zeros(self.values.shape, bool)
        self.age = np.zeros(self.values.shape, np.uint16)

    @staticmethod
    def shape_for(n_domains: int, resolution: int = DEFAULT_RESOLUTION) -> tuple[int, ...]:
        return (n_domains, len(FACES), resolution, resolution, ANGLES)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.values.shape

    @property
    def n_domains(self) -> int:
        return self.values.shape[0]

    @property
    def nbytes(self) -> int:
        """Memory held: ``values`` (4 B per cell) plus the bool ``recorded`` mask (1 B per cell)."""
        return int(self.values.nbytes + self.recorded.nbytes)

    # --- binning -------------------------------------------------------------------------------

    def cells(self, domains: np.ndarray, points: np.ndarray, directions: np.ndarray,
              lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Flat cell index of rays leaving their domain box.

        Parameters
        ----------
        domains : (n,) int, the box each ray leaves.
        points : (n, 3) the exit points, on the box surface (a little off it is fine: u and v
            are clamped).
        directions : (n, 3) ray directions (any non-zero length), pointing out of the box.
        lo, hi : (D, 3) all domain boxes (e.g. ``Store.domain_boxes()``), indexed by
            ``domains``.

        Returns
        -------
        (n,) int64 indices into ``values.ravel()``; :meth:`unravel` splits them.
        """
        domains = np.asarray(domains, dtype=np.int64).reshape(-1)
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        n = len(domains)
        if len(points) != n or len(d) != n:
            raise ValueError(f"{n} domains but {len(points)} points and {len(d)} directions")
        if n and (domains.min() < 0 or domains.max() >= self.n_domains):
            raise ValueError(f"domain ids must be in 0..{self.n_domains - 1}")
        box_lo = np.asarray(lo, dtype=np.float64)[domains]
        box_hi = np.asarray(hi, dtype=np.float64)[domains]
        rows = np.arange(n)
        face, axis = self._exit_face(points, d, box_lo, box_hi)
        u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
        r = self.resolution
        i = _cell(points[rows, u_axis], box_lo[rows, u_axis], box_hi[rows, u_axis], r)
        j = _cell(points[rows, v_axis], box_lo[rows, v_axis], box_hi[rows, v_axis], r)
        length = np.linalg.norm(d, axis=1)
        cos_theta = np.abs(d[rows, axis]) / np.where(length > 0, length, 1.0)
        cos_bin = (cos_theta >= COS_SPLIT).astype(np.int64)
        phi = np.arctan2(d[rows, v_axis], d[rows, u_axis])  # in [-pi, pi]; 0 along the normal
        # quadrants [0, pi/2) 0, [pi/2, pi) 1, [-pi, -pi/2) 2, [-pi/2, 0) 3 (phi = pi: 2)
        phi_bin = np.floor(phi / (np.pi / 2)).astype(np.int64) % 4
        angle = 4 * cos_bin + phi_bin
        return np.ravel_multi_index((domains, face, i, j, angle), self.shape).astype(np.int64)

    @staticmethod
    def _exit_face(points, d, box_lo, box_hi) -> tuple[np.ndarray, np.ndarray]:
        """(face, axis) of the smallest slab exit distance along each direction."""
        with np.errstate(divide="ignore", invalid="ignore"):
            plane = np.where(d > 0, box_hi, box_lo)
            t = np.where(d != 0, (plane - points) / d, np.inf)
        axis = np.argmin(t, axis=1)
        positive = d[np.arange(len(d)), axis] > 0
        return 2 * axis + positive, axis

    def unravel(self, cells: np.ndarray) -> tuple[np.ndarray, ...]:
        """(domain, face, i, j, angle) arrays of flat cell indices; ``angle // 4`` is the
        cos(theta) bin (1: the upper one, around the normal) and ``angle % 4`` the phi
        quadrant."""
        return np.unravel_index(np.asarray(cells, dtype=np.int64), self.shape)

    # --- recording and prediction --------------------------------------------------------------

    def record(self, cells: np.ndarray, values: np.ndarray) -> None:
        """Keep, in each cell, the largest value recorded there (repeated cells are fine).

        ``values`` are radiances (>= 0); NaN is recorded as +inf (never predicts low).
        """
        cells = np.asarray(cells, dtype=np.int64).reshape(-1)
        values = np.asarray(values, dtype=np.float32).reshape(-1)
        if len(cells) != len(values):
            raise ValueError(f"{len(cells)} cells but {len(values)} values")
        values = np.where(np.isnan(values), np.float32(np.inf), values)
        np.maximum.at(self.values.reshape(-1), cells, values)
        self.recorded.reshape(-1)[cells] = True

    def predict(self, cells: np.ndarray) -> np.ndarray:
        """(n,) float32 recorded maximum per cell; +inf where nothing was recorded."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1)
        return np.where(self.recorded.reshape(-1)[cells], self.values.reshape(-1)[cells],
                        np.float32(np.inf)).astype(np.float32)

    def refresh(self, fresh: Portals, memory: int) -> Portals:
        """Fold in the cells one later frame recorded (``fresh``), and forget the cells no
        frame has recorded for ``memory`` frames; returns self.

        A cell ``fresh`` recorded keeps the larger of its two values (as within a frame:
        "we only keep the maximum radiance") and its age goes to 0; every other recorded cell
        ages by one frame, and at age ``memory`` it is forgotten (unrecorded again: predicted
        high, traced fine, and so recorded afresh the next time a ray crosses it). The paper
        records every ``--portal-interval`` frames only; accumulating lets a frame of few
        paths predict from the crossings of its recent predecessors too.

        Parameters
        ----------
        fresh : portals of the same shape, recorded in one frame (merged over the nodes).
        memory : frames a cell is kept without being recorded again (>= 1).
        """
        if fresh.shape != self.shape:
            raise ValueError(f"cannot refresh portals of shape {self.shape} with {fresh.shape}")
        if int(memory) < 1:
            raise ValueError(f"portal memory must be at least 1 frame, got {memory}")
        aging = self.recorded & (self.age < np.iinfo(np.uint16).max)
        np.add(self.age, 1, out=self.age, where=aging)
        self.merge(fresh)  # an unrecorded cell holds 0, and radiances are >= 0
        self.age[fresh.recorded] = 0
        expired = self.recorded & (self.age >= int(memory))
        self.recorded[expired] = False
        self.values[expired] = 0
        self.age[expired] = 0
        return self

    def merge(self, other: Portals) -> Portals:
        """Fold ``other`` in (element-wise MAX of values, OR of the masks); returns self."""
        if other.shape != self.shape:
            raise ValueError(f"cannot merge portals of shape {other.shape} into {self.shape}")
        np.maximum(self.values, other.values, out=self.values)
        np.logical_or(self.recorded, other.recorded, out=self.recorded)
        return self

    def copy(self) -> Portals:
        out = Portals(0, self.resolution)
        out.values, out.recorded = self.values.copy(), self.recorded.copy()
        out.age = self.age.copy()
        return out

    def clear(self) -> None:
        """Forget everything (the start of a recording frame)."""
        self.values.fill(0)
        self.recorded.fill(False)
        self.age.fill(0)

    def __eq__(self, other) -> bool:
        return (isinstance(other, Portals) and self.shape == other.shape
                and np.array_equal(self.values, other.values)
                and np.array_equal(self.recorded, other.recorded))

    __hash__ = None  # mutable

    # --- all-reduce ----------------------------------------------------------------------------

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The portals as arrays to all-reduce with :attr:`REDUCE` (views, no copy):

        * ``portal_values``: the float32 values as (D * 6, R, R, 8), combined by MAX (the wire
          codec sends at most 4 dimensions);
        * ``portal_recorded``: the mask packed to 1 bit per cell, uint8, combined by OR (the
          OR of packed bits is the packed OR).
        """
        d, faces, r, _, angles = self.shape
        return {"portal_values": self.values.reshape(d * faces, r, r, angles),
                "portal_recorded": np.packbits(self.recorded.reshape(-1))}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Portals:
        """The portals :meth:`to_arrays` (or an all-reduce of it) describes (copied).

        Raises
        ------
        ValueError
            Arrays of the wrong shape or dtype.
        """
        values = np.asarray(arrays["portal_values"])
        packed = np.asarray(arrays["portal_recorded"])
        faces = len(FACES)
        if (values.ndim != 4 or values.shape[0] % faces or values.shape[1] != values.shape[2]
                or values.shape[3] != ANGLES or values.dtype != np.float32):
            raise ValueError(f"portal values must be (D * 6, R, R, 8) float32, got "
                             f"{values.shape} {values.dtype}")
        if packed.dtype != np.uint8 or packed.shape != ((values.size + 7) // 8,):
            raise ValueError(f"portal mask must be ({(values.size + 7) // 8},) uint8, got "
                             f"{packed.shape} {packed.dtype}")
        out = cls(values.shape[0] // faces, values.shape[1])
        out.values[...] = values.reshape(out.shape)
        out.recorded[...] = np.unpackbits(packed, count=values.size).astype(bool).reshape(
            out.shape)
        return out


@dataclass(frozen=True)
class Accuracy:
    """How well predicted radiances classify crossings against the radiance they brought.

    Attributes
    ----------
    crossings : crossings classified.
    agree : those whose predicted class (<= threshold: low, else high) is the actual one.
    predicted_low : those predicted low (they would go to the simplified model).
    false_low : predicted low, actually high (light the simplified model may lose).
    false_high : predicted high, actually low (a ray traced fine that need not be).
    unrecorded : predicted +inf: their cell was never recorded (so predicted high).
    """

    crossings: int
    agree: int
    predicted_low: int
    false_low: int
    false_high: int
    unrecorded: int = 0

    @property
    def acc(self) -> float | None:
        """ACC, the share of crossings classified right (None without crossings)."""
        return self.agree / self.crossings if self.crossings else None

    @property
    def simplified_share(self) -> float | None:
        """Simple/total, the share of crossings predicted low (None without crossings)."""
        return self.predicted_low / self.crossings if self.crossings else None

    def counters(self, prefix: str) -> dict[str, int]:
        """The counts as ``{prefix + name: count}`` (integers: they add up over frames)."""
        return {f"{prefix}{k}": int(getattr(self, k)) for k in _ACCURACY_COUNTS}

    @classmethod
    def from_counters(cls, counters: dict, prefix: str) -> Accuracy | None:
        """The inverse of :meth:`counters` (None if ``counters`` has none of them)."""
        if f"{prefix}crossings" not in counters:
            return None
        return cls(*(int(counters[f"{prefix}{k}"]) for k in _ACCURACY_COUNTS))

    def __add__(self, other: Accuracy) -> Accuracy:
        """The counts of both sets of crossings together (frames, nodes)."""
        return Accuracy(*(getattr(self, k) + getattr(other, k) for k in _ACCURACY_COUNTS))


_ACCURACY_COUNTS = ("crossings", "agree", "predicted_low", "false_low", "false_high",
                    "unrecorded")


def prediction_accuracy(predicted: np.ndarray, actual: np.ndarray, threshold: float = 0.5
                        ) -> Accuracy:
    """Classify crossings by predicted radiance and compare with the radiance they brought.

    A crossing is low when its radiance is at most ``threshold`` (the routing rule: a
    prediction <= threshold sends the ray to the simplified model), else high. Unrecorded
    cells predict +inf (high); NaN counts as high on either side.

    Parameters
    ----------
    predicted : (n,) predicted radiance per crossing (e.g. ``Portals.predict(cells)``).
    actual : (n,) radiance each crossing actually brought back (``CrossingLog.crossings``).
    threshold : tau.

    Returns
    -------
    Accuracy with the counts; ``acc`` and ``simplified_share`` are ratios of them.
    """
    predicted = np.asarray(predicted, dtype=np.float64).reshape(-1)
    actual = np.asarray(actual, dtype=np.float64).reshape(-1)
    if len(predicted) != len(actual):
        raise ValueError(f"{len(predicted)} predictions but {len(actual)} actual values")
    low = predicted <= threshold
    actual_low = actual <= threshold
    return Accuracy(crossings=len(low), agree=int(np.count_nonzero(low == actual_low)),
                    predicted_low=int(np.count_nonzero(low)),
                    false_low=int(np.count_nonzero(low & ~actual_low)),
                    false_high=int(np.count_nonzero(~low & actual_low)),
                    unrecorded=int(np.count_nonzero(np.isposinf(predicted))))


class CrossingLog:
    """Per path of a frame: the portal cell its depth-1 ray crossed and the radiance it brought.

    Filled during an instrumented recording frame (every depth-1 ray traced fine), on the
    node where the crossing ray's hit became final (:meth:`crossed`) and on the nodes where
    its shadow rays came through unblocked (:meth:`lit`); nodes then combine their logs by
    MAX (:attr:`REDUCE`): a path crosses at most once, so its cell comes from one node, and
    the value is the largest over its lit shadow rays, as in the portals themselves.

    Parameters
    ----------
    n_paths : N, the pass's paths (width x height x its samples), indexed by
        ``ImageSchedule._path_ids``.

    Attributes
    ----------
    cell : (N,) int64 flat portal cell crossed, -1 where the path crossed none.
    value : (N,) float32 radiance brought back (0 where no shadow ray of it was lit).
    """

    REDUCE = {"crossing_cell": "max", "crossing_value": "max"}

    def __init__(self, n_paths: int):
        self.cell = np.full(int(n_paths), -1, np.int64)
        self.value = np.zeros(int(n_paths), np.float32)

    def crossed(self, paths: np.ndarray, cells: np.ndarray) -> None:
        """Paths ((m,) frame path ids) whose depth-1 ray crossed its portal in ``cells``."""
        self.cell[np.asarray(paths, dtype=np.int64)] = cells

    def lit(self, paths: np.ndarray, values: np.ndarray) -> None:
        """Lit shadow rays of crossing rays: keep each path's largest value (NaN: +inf)."""
        values = np.asarray(values, dtype=np.float32)
        values = np.where(np.isnan(values), np.float32(np.inf), values)
        np.maximum.at(self.value, np.asarray(paths, dtype=np.int64), values)

    def crossings(self) -> tuple[np.ndarray, np.ndarray]:
        """(cells (m,) int64, values (m,) float32) of the paths that crossed a portal."""
        crossed = self.cell >= 0
        return self.cell[crossed], self.value[crossed]

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"crossing_cell": self.cell, "crossing_value": self.value}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> CrossingLog:
        cell = np.asarray(arrays["crossing_cell"], dtype=np.int64)
        value = np.asarray(arrays["crossing_value"], dtype=np.float32)
        if cell.shape != value.shape or cell.ndim != 1:
            raise ValueError(f"crossing log arrays must be two (N,) arrays, got {cell.shape} "
                             f"and {value.shape}")
        out = cls(0)
        out.cell, out.value = cell.copy(), value.copy()
        return out


def _cell(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, r: int) -> np.ndarray:
    """clamp(floor(r * (x - lo) / (hi - lo)), 0, r - 1); cell 0 on a flat side."""
    extent = hi - lo
    u = np.divide(x - lo, extent, out=np.zeros_like(x), where=extent > 0)
    return np.clip(np.floor(r * u), 0, r - 1).astype(np.int64)
