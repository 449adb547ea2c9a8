"""The feature-filter language (Sjövall §3.3, Appendix A), parsed into typed dataclasses.

A filter is a list of segments (cross-section patterns searched along rows and,
rotated, along columns) and post-processing steps (``h-and-v``, ``connect``,
``findrectangle``). Lengths and widths are in category tiles, or in metres when
written with an ``m`` suffix (``connect simple 12m 80m 12m 80m``,
``beginsubsegment 2m 24m``, ``findrectangle 100m 100m 5``): those are turned
into tile counts for the category tile size the filter runs on
(``resolve_lengths``), so a filter keeps its meaning when the tile size or the
DTM resolution changes. Every error names its line, so a user posting a filter
with a job gets told where it breaks.

Orientation codes are two digits ``ab`` (an edge between boundary points a and b,
stored with a < b), ``aa`` (an extreme point) or ``0`` (no edge); directions are
numbered counter-clockwise from east: 1 E, 2 NE, 3 N, 4 NW, 5 W, 6 SW, 7 S, 8 SE.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal, TypeAlias, cast

from terrasift.errors import FilterSyntaxError
from terrasift.workers.categories import ORIENTATIONS

#: maximal segment length in tiles; matches are tracked as 64-bit length sets
MAX_SEGMENT_TILES = 63


def rotate_direction(d: int, quarter_turns: int = 1) -> int:
    """Direction 1–8 turned clockwise by ``quarter_turns`` × 90° (0 stays 0)."""
    if d == 0:
        return 0
    return (d - 1 - 2 * quarter_turns) % 8 + 1


def rotate_orientation(code: int, quarter_turns: int = 1) -> int:
    """Orientation code with both direction digits turned clockwise, normalised a ≤ b."""
    if code == 0:
        return 0
    a, b = divmod(code, 10)
    a, b = sorted((rotate_direction(a, quarter_turns), rotate_direction(b, quarter_turns)))
    return 10 * a + b


@dataclass(frozen=True)
class Metres:
    """A length written in metres (``12m``); becomes a tile count in ``resolve_lengths``."""

    value: float

    def text(self) -> str:
        return f"{self.value:g}m"

    def tiles(self, tile_size: float, bound: Literal["min", "max", "size"]) -> int:
        """Tile count: a minimum rounds down (to at least one tile) and a maximum up
        (the object sought keeps its full range), a window size up (the window
        covers at least the length)."""
        t = self.value / tile_size
        if bound == "min":  # a length above 0 is at least one tile
            return max(1, int(math.floor(t + 1e-9)))
        return int(math.ceil(t - 1e-9))


#: a length: a whole number of tiles, or Metres until ``resolve_lengths`` turns it into
#: tiles (typed loosely: the search and connect steps only ever see resolved filters)
Length: TypeAlias = Any


def _text(v: Length | None) -> str:
    if v is None:
        return "-1"
    return v.text() if isinstance(v, Metres) else str(v)


def _le(a: Length | None, b: Length | None) -> bool:
    """a <= b where both are known in one unit (True when they cannot be compared yet)."""
    if a is None or b is None or isinstance(a, Metres) != isinstance(b, Metres):
        return True
    if isinstance(a, Metres):
        return a.value <= b.value
    return a <= b


@dataclass(frozen=True)
class ValueSet:
    """Allowed values of one category property: ``values`` (None = any), or all but them."""

    values: frozenset[int] | None = None
    negate: bool = False

    def allows(self, v: int) -> bool:
        if self.values is None:
            return True
        return (v in self.values) != self.negate

    def map(self, fn: Callable[[int], int]) -> ValueSet:
        if self.values is None:
            return self
        return replace(self, values=frozenset(fn(v) for v in self.values))

    def text(self) -> str:
        if self.values is None:
            return "any"
        body = " ".join(str(v) for v in sorted(self.values))
        return f"not {body}" if self.negate else body


@dataclass(frozen=True)
class CategorySpec:
    """One allowed category: a tile matches when all three properties allow it (or none, with ``negate``)."""

    inclination: ValueSet = ValueSet()
    state: ValueSet = ValueSet()
    orientation: ValueSet = ValueSet()
    negate: bool = False
    height: ValueSet = ValueSet()
    """The tile's height in decimetres as the flatness test sees it (``Categories.relief10``)."""
    lying_height: ValueSet = ValueSet()
    """``height`` of the tile as it lies, before ``detrend`` sets it on its regional slope
    (``Categories.lying10``); on a grid without ``detrend`` the same as ``height``."""
    clear: bool = False
    """The tile must be clearly not flat: higher than the flatness threshold by more
    than the noise of the DTM's tile slopes explains (``Categories.clear``)."""
    rise: ValueSet = ValueSet()
    """The direction (1-8, 0 none) the tile's plane rises toward, flat or not, where its
    gradient exceeds what the DTM's slope noise explains (``Categories.rise``)."""
    grade: ValueSet = ValueSet()
    """The tile plane's gradient in whole multiples of the DTM's slope noise
    (``Categories.grade``): ``grade not 0 1 2 3 4`` is at least five times the noise."""


@dataclass(frozen=True)
class SubSegment:
    """A run of ``min_len``..``max_len`` tiles, each matching one of ``categories``."""

    min_len: Length
    max_len: Length
    categories: tuple[CategorySpec, ...]
    exclude: bool = False
    max_errors: int = 0


@dataclass(frozen=True)
class Segment:
    """A cross-section pattern; total length limits are None when not given."""

    subsegments: tuple[SubSegment, ...]
    min_total: Length | None = None
    max_total: Length | None = None
    invert: bool = False
    direction: Literal["both", "horizontal", "vertical"] = "both"

    @property
    def longest(self) -> int:
        """Longest match in tiles (a resolved segment only)."""
        top = sum(s.max_len for s in self.subsegments)
        return top if self.max_total is None else min(top, self.max_total)

    @property
    def in_tiles(self) -> bool:
        vals = [self.min_total, self.max_total]
        vals += [v for s in self.subsegments for v in (s.min_len, s.max_len)]
        return not any(isinstance(v, Metres) for v in vals)


@dataclass(frozen=True)
class Connect:
    """``connect method minlen maxlen minwid maxwid [maxerror%]``; -1 disables a limit (stored as None)."""

    method: Literal["edge", "simple", "segment"]
    min_length: Length | None = None
    max_length: Length | None = None
    min_width: Length | None = None
    max_width: Length | None = None
    max_error: float = 0.0


@dataclass(frozen=True)
class Rectangle:
    """``findrectangle w h err%``: rectangles of w × h tiles with at most err % unmarked."""

    width: Length
    height: Length
    error: float


@dataclass(frozen=True)
class Aspect:
    """``aspect min max``: objects whose length / width lies in [min, max]; -1 (None) leaves a side open."""

    min: float | None = None
    max: float | None = None


@dataclass(frozen=True)
class Filter:
    """A parsed filter file.

    ``join`` (``join <gap>``): objects of the filter closer than the gap (a
    length, or ``width``: the narrower one's own width) become one object when
    the joined object is no wider than 1.5 times the wider piece (pieces of one
    ditch, not two parallel ditches). Joining comes before the connect limits,
    so pieces too short alone count together.
    """

    name: str
    segments: tuple[Segment, ...]
    h_and_v: bool = False
    connect: Connect | None = None
    rectangle: Rectangle | None = None
    steps: tuple[str, ...] = field(default=(), compare=False)
    aspect: Aspect | None = None
    join: Length | Literal["width"] | None = None
    join_aligned: Length | None = None
    """``join <gap> <aligned gap>``: pieces lined up end to end (long axes within 20° of
    each other and of the gap between them) also join across gaps up to the second
    length (a ditch whose middle the categories miss)."""
    step: Metres | None = None
    """``step <metres>``: run on tiles starting every step (overlapping tiles), finer than the tile grid."""
    hull: bool = False
    solidity: float | None = None
    """``solidity <min>``: objects covering at least this share of their convex hull (a
    closed outline filled, not the open half-ring at a ridge's end)."""
    """``fill hull``: each object is the convex hull of its tiles (an outline found on part of
    its ring, as a hill's on a slope, closed) before it is measured and limited."""
    detrend: Metres | None = None
    """``detrend <metres>``: run on categories of tiles set on their regional slope (the
    median tile gradient over a window this wide), so a narrow object on a slope is
    categorised as on level ground."""
    clear_share: float | None = None
    """``clear-share <share>``: objects (before joining) whose tiles that are not flat are
    clearly not flat (``Categories.clear``) for at least this share; on a DTM whose tile
    slopes carry the noise of sparse points, chance patterns are made of tiles only just
    past the flatness threshold."""
    h_and_v_share: float | None = None
    """``h-and-v <share>``: a group of tiles marked both ways is kept only when it is at
    least this share of the tiles marked either way that it connects to (a bowl is
    crossed both ways nearly everywhere; the corner where a row-strip meets a
    column-strip is a small part of both)."""

    surround: tuple[Length, float] | None = None
    """``surround <distance> <share>``: objects (before joining) around which, within the
    distance, at most this share of the tiles that the filter does not mark are not
    flat. A ditch is a narrow incision into smoother ground; on a rough, hummocky slope
    every hollow between hummocks has banks like a short ditch, and so has the ground
    around it."""

    enclosed: tuple[Length, int] | None = None
    """``enclosed <distance> <sectors>``: objects (before joining) around which, within the
    distance, tiles rising away from the object (inclined within 45° of the bearing from
    the object's centre) lie in at least this many of the 8 bearing sectors (45° each,
    centred on the eight directions). A pond is a hollow with banks all around; level
    ground between two long rises (a road embankment and a ridge) has banks on two sides."""

    isolated: tuple[Length, float] | None = None
    """``isolated <distance> <share>``: objects (before joining) around which, within the
    distance, at most this share of the tiles with data are inclined other than rising
    toward the object (within 45° of the bearing to its centre). A hill's flanks fade
    into ground that is flat or still rises toward it; the rounded end of a ridge, closed
    into an outline of its own, runs on into the ridge's flanks, inclined across it."""

    yields: tuple[tuple[str, Length, float] | tuple[str, Length, float, Length], ...] = ()
    """``yield <filter> <distance> <share> [<length>]`` (each once per filter named): objects
    of which at least this share of the area lies within the distance (tiles of the category
    tile size, or metres) of an object of the named filter are dropped once every filter has
    run (Sjövall §5.3.1: filters in an order of priority, an object found by the first
    taken out before the next looks). A road cut into a slope is, on the ditch filter's
    detrended tiles, a trough falling to the foot of its uphill wall. With a length, an
    object is also dropped when no part of it beyond the distance is that long: what is
    left once the other object's ground is taken out must still be an object (pieces on a
    cut road's walls, joined end to end to a chance piece off the road, are not a ditch)."""
    join_line: Length | None = None
    """``join-line <gap>``: objects (within the connect limits on their own) lying on one
    line, each one's centre within half the narrower one's width of the other's long
    axis, join across gaps up to this length: a straight road whose middle the
    categories miss over a stretch, found as two pieces on one centre line."""
    clear_exempt: float | None = None
    """``clear-share <share> <sigmas>``: the share is not asked of an object (before
    joining) of at least as many tiles as the connect step's smallest length where the
    flatness threshold is at least this many slope-noise heights above level
    (``Categories.flat_sigmas``): there noise cannot tip a level tile past the threshold,
    and a shallow object's tiles just past it are real."""
    diagonal: Length | None = None
    """``diagonal <width>``: the segments are also searched on tiles turned by 45° (rows
    and columns along the grid's diagonals), with every subsegment that is not excluded
    (the strip) at least this long, and their marks set back on the filter's grid
    (``features.turned``): a strip crossing the grid obliquely is crossed squarely on
    one grid or the other."""
    banks: tuple[str, ...] = ()
    """``bank <filter>``: an object lying on the flank of an object of the named filter
    (at least half its area within that object, whose middle, over the object's length,
    lies beside the object's strip: more than half the object's width off its axis) is
    that object's bank: dropped, and nothing yields to it. A flat-bottomed ditch along a
    slope's contour has a downhill bank that is level across (its rise out of the ditch
    cancels the slope) between the ditch's floor and the hillside falling on: a strip
    between a rise and a fall, as a road cut into the slope, but the ditch's floor lies
    beside it where a cut road's floor is the road."""

    splits: tuple[str, ...] = ()
    """``split <filter>``: once every filter has run, after the banks and before the yields,
    an object lying across objects of the named filter is cut along them: its parts off
    them are joined again and measured as the filter's own pieces are (``join``, the
    connect limits), and where they make two objects or more these replace it (each then
    yields or not on its own). An object the cut leaves whole, or as one object (a ditch
    crossing a road joins again end to end across it), is kept as it was. The ditch
    filter's marks run over a road's ground between the ditches along both its sides
    (the level top of a road on a slope reads as a bank on the regional slope; a cut's
    end wall), and one object lay on both ditches and the road."""

    edges: float | None = None
    """``edges <height>``: once every filter has run, and before the banks and yields, an
    object is read on the DTM across its whole length (``features.edges``) and dropped
    when it is a trough (the ground past both its sides rising on, at more than half its
    stations) or a verge (a step of more than ``height`` metres past one side at more
    than half its stations, with another object of the filter beside it there, and none
    past the other side). Needs the DTM; without it nothing is dropped."""

    edges_tilt: float | None = None
    """``edges <height> <tilt>``: also drop an object that leans with the slope it lies on
    (``features.edges``): its strip, fitted across over the whole object, falls by more
    than ``tilt`` metres per metre toward the side the ground past both its sides falls
    to, and that ground falls more steeply than the strip."""

    majority: bool = False
    """``majority`` (with ``findrectangle``): a tile the segments miss but which is not
    ``clear`` (its excess over the flatness threshold within what the DTM's slope noise
    explains) is marked when more than half of the tiles with data in the 3 × 3 tiles
    around it (itself included) are marked. On a hillside just under the threshold the
    noise of a tile's fitted slope tips single tiles past it at random; the tile's
    neighbours on the same plane read it again."""

    yield_deeper: tuple[tuple[str, float], ...] = ()
    """``yield <filter> ... deeper <k>``: (filter name, k) of the yields that also ask
    for depth: an object yields to an object of the named filter only if its median DTM
    height is not more than k times the DTM's noise σ (the flatness tests' noise) below
    the median height of that filter's objects alongside it (within the yield distance
    plus their own width of it). A ditch beside a road lies clearly below the road; a
    trough the ditch filter finds in the road itself lies at the road's own height."""

    @property
    def makes_objects(self) -> bool:
        return self.connect is not None or self.rectangle is not None


# --------------------------------------------------------------------------- parsing


def parse_filter(text: str, name: str = "user") -> Filter:
    """Parse filter ``text``; raises FilterSyntaxError naming the line and the reason."""
    return _Parser(text, name).parse()


class _Parser:
    def __init__(self, text: str, name: str):
        self.name = name
        self.lines: list[tuple[int, list[str]]] = []
        for no, raw in enumerate(text.splitlines(), start=1):
            body = raw.split("//", 1)[0].strip()
            if body:
                self.lines.append((no, body.lower().split()))
        self.pos = 0

    def error(self, msg: str, line: int | None) -> FilterSyntaxError:
        return FilterSyntaxError(msg, line=line, name=self.name)

    def next(self) -> tuple[int, list[str]] | None:
        if self.pos >= len(self.lines):
            return None
        self.pos += 1
        return self.lines[self.pos - 1]

    def ints(self, words: list[str], line: int, what: str, lo: int | None = None) -> list[int]:
        out = []
        for w in words:
            try:
                v = int(w)
            except ValueError:
                raise self.error(f"{what}: expected a whole number, got {w!r}", line) from None
            if lo is not None and v < lo:
                raise self.error(f"{what}: {v} is below {lo}", line)
            out.append(v)
        return out

    def lengths(self, words: list[str], line: int, what: str, lo: int) -> list[Length]:
        """Whole numbers of tiles (at least ``lo``) or metres written ``<number>m`` (above 0)."""
        out: list[Length] = []
        for w in words:
            if w.endswith("m"):
                try:
                    v = float(w[:-1])
                except ValueError:
                    raise self.error(
                        f"{what}: expected tiles or metres (e.g. 12m), got {w!r}", line
                    ) from None
                if not (v > 0 and math.isfinite(v)):
                    raise self.error(f"{what}: a length in metres must be above 0, got {w!r}", line)
                out.append(Metres(v))
            else:
                out += self.ints([w], line, what, lo=lo)
        return out

    def numbers(self, words: list[str], line: int, what: str) -> list[float]:
        try:
            return [float(w) for w in words]
        except ValueError:
            raise self.error(f"{what}: expected numbers, got {' '.join(words)!r}", line) from None

    def parse(self) -> Filter:
        segments: list[Segment] = []
        h_and_v = False
        connect: Connect | None = None
        rect: Rectangle | None = None
        aspect: Aspect | None = None
        join: Length | Literal["width"] | None = None
        join_aligned: Length | None = None
        step: Metres | None = None
        detrend: Metres | None = None
        hull = False
        solidity: float | None = None
        clear_share: float | None = None
        clear_exempt: float | None = None
        surround: tuple[Length, float] | None = None
        share: float | None = None
        yields: list[tuple[str, Length, float] | tuple[str, Length, float, Length]] = []
        banks: list[str] = []
        splits: list[str] = []
        deeper: list[tuple[str, float]] = []
        edges: float | None = None
        edges_tilt: float | None = None
        enclosed: tuple[Length, int] | None = None
        isolated: tuple[Length, float] | None = None
        join_line: Length | None = None
        diagonal: Length | None = None
        majority = False
        steps: list[str] = []
        last_line = self.lines[-1][0] if self.lines else 1
        while (item := self.next()) is not None:
            no, words = item
            key, args = words[0], words[1:]
            if key == "beginsegment":
                if steps:
                    raise self.error("segments must come before connect/h-and-v/findrectangle", no)
                segments.append(self.segment(no, args))
            elif key == "h-and-v":
                if h_and_v or len(args) > 1:
                    raise self.error("h-and-v takes at most one share (0-1), once", no)
                if args:
                    (share,) = self.numbers(args, no, "h-and-v")
                    if not 0 < share <= 1:
                        raise self.error("h-and-v share is above 0 and at most 1", no)
                h_and_v = True
                steps.append("h-and-v")
            elif key == "connect":
                if connect is not None or rect is not None:
                    raise self.error("only one connect or findrectangle step is allowed", no)
                connect = self.connect(no, args)
                steps.append("connect")
            elif key == "aspect":
                if aspect is not None or len(args) != 2:
                    raise self.error("aspect takes min and max length/width once (-1: open)", no)
                lo, hi = (None if v == -1 else v for v in self.numbers(args, no, "aspect"))
                if any(v is not None and v < 1 for v in (lo, hi)):
                    raise self.error("aspect limits are ratios of at least 1 (or -1)", no)
                if lo is not None and hi is not None and lo > hi:
                    raise self.error("aspect: min exceeds max", no)
                aspect = Aspect(lo, hi)
                steps.append("aspect")
            elif key == "step":
                if steps or step is not None:
                    raise self.error("step comes once, before the segments", no)
                if len(args) != 1 or not args[0].endswith("m"):
                    raise self.error("step takes one length in metres, e.g. step 1m", no)
                step = self.lengths(args, no, "step", lo=1)[0]
            elif key == "diagonal":
                if steps or segments or diagonal is not None or len(args) != 1:
                    raise self.error("diagonal takes one width, once, before the segments", no)
                diagonal = self.lengths(args, no, "diagonal", lo=1)[0]
            elif key == "detrend":
                if steps or segments or detrend is not None:
                    raise self.error("detrend comes once, before the segments", no)
                if len(args) != 1 or not args[0].endswith("m"):
                    raise self.error("detrend takes one window in metres, e.g. detrend 24m", no)
                detrend = self.lengths(args, no, "detrend", lo=1)[0]
            elif key == "solidity":
                if solidity is not None or len(args) != 1:
                    raise self.error("solidity takes one share (0-1) once", no)
                (solidity,) = self.numbers(args, no, "solidity")
                if not 0 < solidity <= 1:
                    raise self.error("solidity is a share above 0 and at most 1", no)
                steps.append("solidity")
            elif key == "clear-share":
                if clear_share is not None or len(args) not in (1, 2):
                    raise self.error(
                        "clear-share takes one share (0-1) and optionally a noise multiple, once",
                        no,
                    )
                values = self.numbers(args, no, "clear-share")
                clear_share = values[0]
                if not 0 < clear_share <= 1:
                    raise self.error("clear-share is a share above 0 and at most 1", no)
                if len(values) == 2:
                    clear_exempt = values[1]
                    if not clear_exempt > 0:
                        raise self.error("clear-share's noise multiple is above 0", no)
                steps.append("clear-share")
            elif key == "surround":
                if surround is not None or len(args) != 2:
                    raise self.error("surround takes a distance and a share (0-1) once", no)
                (dist,) = self.lengths(args[:1], no, "surround", lo=1)
                (most,) = self.numbers(args[1:], no, "surround")
                if not 0 <= most <= 1:
                    raise self.error("surround share is between 0 and 1", no)
                surround = (dist, most)
                steps.append("surround")
            elif key == "enclosed":
                if enclosed is not None or len(args) != 2:
                    raise self.error("enclosed takes a distance and a number of sectors once", no)
                (dist,) = self.lengths(args[:1], no, "enclosed", lo=1)
                (sectors,) = self.ints(args[1:], no, "enclosed", lo=1)
                if sectors > 8:
                    raise self.error("enclosed: at most 8 sectors", no)
                enclosed = (dist, sectors)
                steps.append("enclosed")
            elif key == "isolated":
                if isolated is not None or len(args) != 2:
                    raise self.error("isolated takes a distance and a share (0-1) once", no)
                (dist,) = self.lengths(args[:1], no, "isolated", lo=1)
                (most,) = self.numbers(args[1:], no, "isolated")
                if not 0 <= most <= 1:
                    raise self.error("isolated share is between 0 and 1", no)
                isolated = (dist, most)
                steps.append("isolated")
            elif key == "yield":
                if len(args) >= 2 and args[-2] == "deeper":
                    (k,) = self.numbers(args[-1:], no, "yield deeper")
                    if not (k >= 0 and math.isfinite(k)):
                        raise self.error("yield deeper takes a noise multiple of at least 0", no)
                    deeper.append((args[0], k))
                    args = args[:-2]
                if len(args) not in (3, 4) or any(y[0] == args[0] for y in yields):
                    raise self.error(
                        "yield takes a filter name, a distance, a share (0-1), optionally"
                        " a length and optionally 'deeper <noise multiple>', once per name",
                        no,
                    )
                (reach,) = self.lengths(args[1:2], no, "yield", lo=0)
                (most,) = self.numbers(args[2:3], no, "yield")
                if not 0 < most <= 1:
                    raise self.error("yield share is above 0 and at most 1", no)
                if args[0] == self.name:
                    raise self.error("a filter cannot yield to itself", no)
                if len(args) == 4:
                    (rest,) = self.lengths(args[3:], no, "yield", lo=1)
                    yields.append((args[0], reach, most, rest))
                else:
                    yields.append((args[0], reach, most))
                if "yield" not in steps:
                    steps.append("yield")
            elif key == "bank":
                if len(args) != 1 or args[0] in banks or args[0] == self.name:
                    raise self.error("bank takes another filter's name, once per name", no)
                banks.append(args[0])
                if "bank" not in steps:
                    steps.append("bank")
            elif key == "split":
                if len(args) != 1 or args[0] in splits or args[0] == self.name:
                    raise self.error("split takes another filter's name, once per name", no)
                splits.append(args[0])
                if "split" not in steps:
                    steps.append("split")
            elif key == "edges":
                msg = (
                    "edges takes one height in metres, above 0 and at most 5, and optionally"
                    " a tilt in metres per metre, above 0 and at most 1, once"
                )
                if len(args) not in (1, 2) or edges is not None:
                    raise self.error(msg, no)
                edges, *more = self.numbers(args, no, "edges")
                edges_tilt = more[0] if more else None
                if not 0 < edges <= 5 or (edges_tilt is not None and not 0 < edges_tilt <= 1):
                    raise self.error(msg, no)
                steps.append("edges")
            elif key == "fill":
                if hull or args != ["hull"]:
                    raise self.error("fill takes 'hull', once", no)
                hull = True
                steps.append("fill")
            elif key == "join":
                if join is not None or len(args) not in (1, 2):
                    raise self.error(
                        "join takes a gap (tiles, metres or 'width') and optionally a gap for"
                        " pieces lined up end to end, once",
                        no,
                    )
                join = "width" if args[0] == "width" else self.lengths(args, no, "join", lo=1)[0]
                if len(args) == 2:
                    join_aligned = self.lengths(args[1:], no, "join", lo=1)[0]
                steps.append("join")
            elif key == "join-line":
                if join_line is not None or len(args) != 1:
                    raise self.error("join-line takes one gap (tiles or metres), once", no)
                join_line = self.lengths(args, no, "join-line", lo=1)[0]
                steps.append("join-line")
            elif key == "majority":
                if majority or args:
                    raise self.error("majority takes no parameters, once", no)
                majority = True
                steps.append("majority")
            elif key == "findrectangle":
                if connect is not None or rect is not None:
                    raise self.error("only one connect or findrectangle step is allowed", no)
                if len(args) != 3:
                    raise self.error("findrectangle needs width, height and error %", no)
                w, h = self.lengths(args[:2], no, "findrectangle", lo=1)
                (err,) = self.numbers(args[2:], no, "findrectangle error")
                if not 0 <= err < 100:
                    raise self.error("findrectangle error % must be in [0, 100)", no)
                rect = Rectangle(w, h, err)
                steps.append("findrectangle")
            else:
                raise self.error(f"unexpected {key!r} outside a segment", no)
        if not segments:
            raise self.error("a filter needs at least one beginsegment … endsegment", last_line)
        if (
            aspect is not None
            or join is not None
            or join_line is not None
            or hull
            or solidity is not None
            or clear_share is not None
            or surround is not None
            or enclosed is not None
            or isolated is not None
        ) and connect is None:
            raise self.error(
                "aspect, join, join-line, fill, solidity, clear-share, surround, enclosed and isolated"
                " need a connect step",
                last_line,
            )
        if diagonal is not None and (step is None or detrend is not None):
            raise self.error("diagonal needs a step and no detrend", last_line)
        if majority and rect is None:
            raise self.error("majority needs a findrectangle step", last_line)
        if yields and connect is None and rect is None:
            raise self.error("yield needs a connect or findrectangle step", last_line)
        if banks and connect is None and rect is None:
            raise self.error("bank needs a connect or findrectangle step", last_line)
        if edges is not None and connect is None:
            raise self.error("edges needs a connect step", last_line)
        if splits and connect is None:
            raise self.error("split needs a connect step", last_line)
        return Filter(
            self.name,
            tuple(segments),
            h_and_v,
            connect,
            rect,
            tuple(steps),
            aspect,
            join,
            join_aligned,
            step,
            hull,
            solidity,
            detrend,
            clear_share,
            share,
            surround,
            enclosed,
            isolated,
            tuple(yields),
            join_line,
            banks=tuple(banks),
            splits=tuple(splits),
            clear_exempt=clear_exempt,
            diagonal=diagonal,
            majority=majority,
            yield_deeper=tuple(deeper),
            edges=edges,
            edges_tilt=edges_tilt,
        )

    def segment(self, start: int, args: list[str]) -> Segment:
        lo = hi = None
        if args:
            if len(args) != 2:
                raise self.error(
                    "beginsegment takes no parameters or min and max total length", start
                )
            lo, hi = self.lengths(args, start, "beginsegment", lo=1)
            if not _le(lo, hi):
                raise self.error(f"beginsegment: min {lo} exceeds max {hi}", start)
        subs: list[SubSegment] = []
        invert = False
        direction: Literal["both", "horizontal", "vertical"] = "both"
        while (item := self.next()) is not None:
            no, words = item
            key, rest = words[0], words[1:]
            if key == "endsegment":
                if not subs:
                    raise self.error("a segment needs at least one subsegment", no)
                seg = Segment(tuple(subs), lo, hi, invert, direction)
                if seg.in_tiles:
                    _check_segment(seg, lambda msg, at: self.error(msg, at), start, no)
                return seg
            if rest and key in ("invert", "horizontal", "vertical"):
                raise self.error(f"{key} takes no parameters", no)
            if key == "invert":
                invert = True
            elif key in ("horizontal", "vertical"):
                if direction != "both":
                    raise self.error("horizontal and vertical are exclusive", no)
                direction = "horizontal" if key == "horizontal" else "vertical"
            elif key == "beginsubsegment":
                subs.append(self.subsegment(no, rest))
            else:
                raise self.error(f"unexpected {key!r} inside a segment", no)
        raise self.error("beginsegment without endsegment", start)

    def subsegment(self, start: int, args: list[str]) -> SubSegment:
        exclude = False
        if args and args[-1] == "exclude":
            exclude, args = True, args[:-1]
        if len(args) != 2:
            raise self.error("beginsubsegment needs min and max length [exclude]", start)
        lo, hi = self.lengths(args, start, "beginsubsegment", lo=0)
        if (isinstance(hi, int) and hi < 1) or not _le(lo, hi):
            raise self.error(f"beginsubsegment: bad length range {lo}..{hi}", start)
        cats: list[CategorySpec] = []
        max_errors = 0
        while (item := self.next()) is not None:
            no, words = item
            key, rest = words[0], words[1:]
            if key == "endsubsegment":
                if not cats:
                    raise self.error("a subsegment needs at least one category", no)
                if isinstance(hi, int) and max_errors >= hi and hi > 0:
                    raise self.error("maxerrors must be below the subsegment's max length", no)
                return SubSegment(lo, hi, tuple(cats), exclude, max_errors)
            if key == "maxerrors":
                if len(rest) != 1:
                    raise self.error("maxerrors takes one number", no)
                (max_errors,) = self.ints(rest, no, "maxerrors", lo=0)
            elif key == "begincategory":
                if rest not in ([], ["not"]):
                    raise self.error("begincategory takes only the optional keyword not", no)
                cats.append(self.category(no, bool(rest)))
            else:
                raise self.error(f"unexpected {key!r} inside a subsegment", no)
        raise self.error("beginsubsegment without endsubsegment", start)

    def category(self, start: int, negate: bool) -> CategorySpec:
        props: dict[str, ValueSet] = {}
        clear = False
        while (item := self.next()) is not None:
            no, words = item
            key, rest = words[0], words[1:]
            if key == "endcategory":
                return CategorySpec(negate=negate, clear=clear, **props)
            if key == "clear":
                if rest or clear:
                    raise self.error("clear takes no values and is given once", no)
                clear = True
                continue
            if key not in (
                "inclination",
                "state",
                "orientation",
                "height",
                "lying-height",
                "rise",
                "grade",
            ):
                raise self.error(f"unexpected {key!r} inside a category", no)
            name = key.replace("-", "_")
            if name in props:
                raise self.error(f"{key} given twice in one category", no)
            props[name] = self.values(no, key, rest)
        raise self.error("begincategory without endcategory", start)

    def values(self, no: int, key: str, words: list[str]) -> ValueSet:
        if words == ["any"]:
            return ValueSet()
        neg = bool(words) and words[0] == "not"
        if neg:
            words = words[1:]
        if not words:
            raise self.error(f"{key} needs values, 'any' or 'not' and values", no)
        vals = self.ints(words, no, key, lo=0)
        if key in ("inclination", "rise"):
            bad = [v for v in vals if v > 8]
            if bad:
                raise self.error(f"{key} must be 0–8, got {bad[0]}", no)
        elif key == "state":
            bad = [v for v in vals if v > 2]
            if bad:
                raise self.error(f"state must be 0, 1 or 2, got {bad[0]}", no)
        elif key in ("height", "lying-height", "grade"):
            bad = [v for v in vals if v > 254]
            if bad:
                raise self.error(f"{key} takes 0–254, got {bad[0]}", no)
        else:
            norm = []
            for v in vals:
                a, b = divmod(v, 10)
                code = 10 * min(a, b) + max(a, b) if v else 0
                if code not in ORIENTATIONS or (v and (a == 0 or b == 0)):
                    raise self.error(
                        f"orientation {words[vals.index(v)]} is not 0, an extreme point aa or an edge "
                        "between boundary points on different sides",
                        no,
                    )
                norm.append(code)
            vals = norm
        return ValueSet(frozenset(vals), neg)

    def connect(self, no: int, args: list[str]) -> Connect:
        if not args or args[0] not in ("edge", "simple", "segment"):
            raise self.error("connect needs an algorithm: edge, simple or segment", no)
        method = cast(Literal["edge", "simple", "segment"], args[0])
        nums = args[1:]
        allowed = 5 if method == "segment" else 4
        if len(nums) not in (4, allowed):
            extra = " [maxerror%]" if method == "segment" else ""
            raise self.error(f"connect {method} needs minlen maxlen minwid maxwid{extra}", no)
        lims = self.lengths(nums[:4], no, "connect", lo=-1)
        err = self.numbers(nums[4:], no, "connect maxerror")[0] if len(nums) == 5 else 0.0
        if not 0 <= err < 100:
            raise self.error("connect maxerror % must be in [0, 100)", no)
        lo_l, hi_l, lo_w, hi_w = (None if v == -1 else v for v in lims)
        for lo, hi, what in ((lo_l, hi_l, "length"), (lo_w, hi_w, "width")):
            if not _le(lo, hi):
                raise self.error(f"connect: min {what} exceeds max {what}", no)
        return Connect(method, lo_l, hi_l, lo_w, hi_w, err)


# --------------------------------------------------------------------------- writing and transforming


def format_filter(f: Filter) -> str:
    """The filter as text that parses back to an equal Filter."""
    out: list[str] = [f"step {f.step.text()}"] if f.step is not None else []
    if f.detrend is not None:
        out.append(f"detrend {f.detrend.text()}")
    if f.diagonal is not None:
        out.append(f"diagonal {_text(f.diagonal)}")
    for seg in f.segments:
        head = (
            "beginsegment"
            if seg.min_total is None
            else f"beginsegment {_text(seg.min_total)} {_text(seg.max_total)}"
        )
        out.append(head)
        if seg.invert:
            out.append("  invert")
        if seg.direction != "both":
            out.append(f"  {seg.direction}")
        for sub in seg.subsegments:
            out.append(
                f"  beginsubsegment {_text(sub.min_len)} {_text(sub.max_len)}"
                + (" exclude" if sub.exclude else "")
            )
            if sub.max_errors:
                out.append(f"    maxerrors {sub.max_errors}")
            for cat in sub.categories:
                out.append("    begincategory" + (" not" if cat.negate else ""))
                out.append(f"      inclination {cat.inclination.text()}")
                out.append(f"      state {cat.state.text()}")
                out.append(f"      orientation {cat.orientation.text()}")
                if cat.height.values is not None:
                    out.append(f"      height {cat.height.text()}")
                if cat.lying_height.values is not None:
                    out.append(f"      lying-height {cat.lying_height.text()}")
                if cat.rise.values is not None:
                    out.append(f"      rise {cat.rise.text()}")
                if cat.grade.values is not None:
                    out.append(f"      grade {cat.grade.text()}")
                if cat.clear:
                    out.append("      clear")
                out.append("    endcategory")
            out.append("  endsubsegment")
        out.append("endsegment")
    for step in f.steps or _default_steps(f):
        if step == "h-and-v":
            out.append("h-and-v" if f.h_and_v_share is None else f"h-and-v {f.h_and_v_share:g}")
        elif step == "connect" and f.connect is not None:
            c = f.connect
            lims = " ".join(
                _text(v) for v in (c.min_length, c.max_length, c.min_width, c.max_width)
            )
            tail = f" {c.max_error:g}" if c.method == "segment" and c.max_error else ""
            out.append(f"connect {c.method} {lims}{tail}")
        elif step == "findrectangle" and f.rectangle is not None:
            r = f.rectangle
            out.append(f"findrectangle {_text(r.width)} {_text(r.height)} {r.error:g}")
        elif step == "aspect" and f.aspect is not None:
            lo, hi = (-1 if v is None else v for v in (f.aspect.min, f.aspect.max))
            out.append(f"aspect {lo:g} {hi:g}")
        elif step == "join" and f.join is not None:
            aligned = "" if f.join_aligned is None else f" {_text(f.join_aligned)}"
            out.append(f"join {f.join if f.join == 'width' else _text(f.join)}{aligned}")
        elif step == "join-line" and f.join_line is not None:
            out.append(f"join-line {_text(f.join_line)}")
        elif step == "fill" and f.hull:
            out.append("fill hull")
        elif step == "solidity" and f.solidity is not None:
            out.append(f"solidity {f.solidity:g}")
        elif step == "clear-share" and f.clear_share is not None:
            exempt = "" if f.clear_exempt is None else f" {f.clear_exempt:g}"
            out.append(f"clear-share {f.clear_share:g}{exempt}")
        elif step == "surround" and f.surround is not None:
            out.append(f"surround {_text(f.surround[0])} {f.surround[1]:g}")
        elif step == "enclosed" and f.enclosed is not None:
            out.append(f"enclosed {_text(f.enclosed[0])} {f.enclosed[1]}")
        elif step == "isolated" and f.isolated is not None:
            out.append(f"isolated {_text(f.isolated[0])} {f.isolated[1]:g}")
        elif step == "yield":
            deeper = dict(f.yield_deeper)
            out += [
                f"yield {y[0]} {_text(y[1])} {y[2]:g}"
                + "".join(f" {_text(r)}" for r in y[3:])
                + (f" deeper {deeper[y[0]]:g}" if y[0] in deeper else "")
                for y in f.yields
            ]
        elif step == "bank":
            out += [f"bank {b}" for b in f.banks]
        elif step == "split":
            out += [f"split {b}" for b in f.splits]
        elif step == "majority" and f.majority:
            out.append("majority")
        elif step == "edges" and f.edges is not None:
            tilt = "" if f.edges_tilt is None else f" {f.edges_tilt:g}"
            out.append(f"edges {f.edges:g}{tilt}")
    return "\n".join(out) + "\n"


def _default_steps(f: Filter) -> tuple[str, ...]:
    steps = ["h-and-v"] if f.h_and_v else []
    if f.connect is not None:
        steps.append("connect")
    if f.rectangle is not None:
        steps.append("findrectangle")
    if f.aspect is not None:
        steps.append("aspect")
    if f.join is not None:
        steps.append("join")
    if f.join_line is not None:
        steps.append("join-line")
    if f.hull:
        steps.append("fill")
    if f.solidity is not None:
        steps.append("solidity")
    if f.clear_share is not None:
        steps.append("clear-share")
    if f.surround is not None:
        steps.append("surround")
    if f.enclosed is not None:
        steps.append("enclosed")
    if f.isolated is not None:
        steps.append("isolated")
    if f.yields:
        steps.append("yield")
    if f.banks:
        steps.append("bank")
    if f.splits:
        steps.append("split")
    if f.majority:
        steps.append("majority")
    if f.edges is not None:
        steps.append("edges")
    return tuple(steps)


def transform_segment(seg: Segment, quarter_turns: int = 0) -> Segment:
    """The segment as searched: inverted when it says so, then rotated clockwise.

    Invert adds 4 to inclinations and swaps states 1 and 2; a rotation turns every
    direction digit (DESIGN §5.7), which is how a west→east pattern becomes north→south.
    """

    def inc(v: int) -> int:
        if seg.invert and v:
            v = (v + 3) % 8 + 1
        return rotate_direction(v, quarter_turns)

    def state(v: int) -> int:
        return {1: 2, 2: 1}.get(v, v) if seg.invert else v

    def ori(v: int) -> int:
        return rotate_orientation(v, quarter_turns)

    subs = tuple(
        replace(
            sub,
            categories=tuple(
                replace(
                    c,
                    inclination=c.inclination.map(inc),
                    rise=c.rise.map(inc),
                    state=c.state.map(state),
                    orientation=c.orientation.map(ori),
                )
                for c in sub.categories
            ),
        )
        for sub in seg.subsegments
    )
    return replace(seg, subsegments=subs, invert=False)


def _check_segment(seg: Segment, error: Callable[[str, int | None], Exception], start, end) -> None:
    """Limits of a segment whose lengths are tile counts."""
    if sum(s.min_len for s in seg.subsegments) == 0:
        raise error("a segment must match at least one tile", end)
    if seg.longest > MAX_SEGMENT_TILES:
        raise error(f"a segment may span at most {MAX_SEGMENT_TILES} tiles", start)
    if seg.min_total is not None and seg.min_total > sum(s.max_len for s in seg.subsegments):
        raise error("beginsegment minimum exceeds what the subsegments can match", start)


def resolve_lengths(f: Filter, tile_size: float) -> Filter:
    """The filter with every length in metres turned into tiles of ``tile_size`` m.

    Minima round down and maxima up, so the range of objects sought is kept; a
    ``findrectangle`` window rounds up. Raises FilterSyntaxError when the tile
    counts break a limit of the language (e.g. a segment longer than 63 tiles).
    """

    def err(msg: str, _line: int | None) -> FilterSyntaxError:
        return FilterSyntaxError(f"{msg} at {tile_size:g} m tiles", name=f.name)

    def t(v: Length | None, bound: Literal["min", "max", "size"]) -> Any:
        return v.tiles(tile_size, bound) if isinstance(v, Metres) else v

    segs = []
    for seg in f.segments:
        if seg.in_tiles:
            segs.append(seg)
            continue
        subs = []
        for sub in seg.subsegments:
            lo, hi = t(sub.min_len, "min"), max(1, t(sub.max_len, "max"))
            if lo > hi:
                raise err(f"subsegment {_text(sub.min_len)}..{_text(sub.max_len)} is empty", None)
            # a run of few large tiles allows fewer misfits than its length in tiles
            errors = min(sub.max_errors, hi - 1)
            subs.append(replace(sub, min_len=lo, max_len=hi, max_errors=errors))
        lo = t(seg.min_total, "min")
        new = replace(
            seg,
            subsegments=tuple(subs),
            min_total=None if lo is None else max(1, lo),
            max_total=t(seg.max_total, "max"),
        )
        _check_segment(new, err, None, None)
        segs.append(new)
    connect = f.connect
    if connect is not None:
        connect = replace(
            connect,
            min_length=t(connect.min_length, "min"),
            max_length=t(connect.max_length, "max"),
            min_width=t(connect.min_width, "min"),
            max_width=t(connect.max_width, "max"),
        )
    rect = f.rectangle
    if rect is not None:
        rect = replace(rect, width=t(rect.width, "size"), height=t(rect.height, "size"))
    join = f.join if f.join == "width" else t(f.join, "size")
    aligned = t(f.join_aligned, "size")
    surround = f.surround
    if surround is not None:
        surround = (max(1, t(surround[0], "size")), surround[1])
    enclosed = f.enclosed
    if enclosed is not None:
        enclosed = (max(1, t(enclosed[0], "size")), enclosed[1])
    isolated = f.isolated
    if isolated is not None:
        isolated = (max(1, t(isolated[0], "size")), isolated[1])
    return replace(
        f,
        segments=tuple(segs),
        connect=connect,
        rectangle=rect,
        join=join,
        join_aligned=aligned,
        join_line=t(f.join_line, "size"),
        diagonal=t(f.diagonal, "min"),
        surround=surround,
        enclosed=enclosed,
        isolated=isolated,
    )
