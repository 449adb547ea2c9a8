"""The feature-filter language (Sjövall §3.3, Appendix A), parsed into typed dataclasses.

A filter is a list of segments (cross-section patterns searched along rows and,
rotated, along columns) and post-processing steps (``h-and-v``, ``connect``,
``findrectangle``). Lengths and widths are in category tiles. Every error names
its line, so a user posting a filter with a job gets told where it breaks.

Orientation codes are two digits ``ab`` (an edge between boundary points a and b,
stored with a < b), ``aa`` (an extreme point) or ``0`` (no edge); directions are
numbered counter-clockwise from east: 1 E, 2 NE, 3 N, 4 NW, 5 W, 6 SW, 7 S, 8 SE.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal, cast

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


@dataclass(frozen=True)
class SubSegment:
    """A run of ``min_len``..``max_len`` tiles, each matching one of ``categories``."""

    min_len: int
    max_len: int
    categories: tuple[CategorySpec, ...]
    exclude: bool = False
    max_errors: int = 0


@dataclass(frozen=True)
class Segment:
    """A cross-section pattern; total length limits are None when not given."""

    subsegments: tuple[SubSegment, ...]
    min_total: int | None = None
    max_total: int | None = None
    invert: bool = False
    direction: Literal["both", "horizontal", "vertical"] = "both"

    @property
    def longest(self) -> int:
        top = sum(s.max_len for s in self.subsegments)
        return top if self.max_total is None else min(top, self.max_total)


@dataclass(frozen=True)
class Connect:
    """``connect method minlen maxlen minwid maxwid [maxerror%]``; -1 disables a limit (stored as None)."""

    method: Literal["edge", "simple", "segment"]
    min_length: int | None = None
    max_length: int | None = None
    min_width: int | None = None
    max_width: int | None = None
    max_error: float = 0.0


@dataclass(frozen=True)
class Rectangle:
    """``findrectangle w h err%``: rectangles of w × h tiles with at most err % unmarked."""

    width: int
    height: int
    error: float


@dataclass(frozen=True)
class Filter:
    """A parsed filter file."""

    name: str
    segments: tuple[Segment, ...]
    h_and_v: bool = False
    connect: Connect | None = None
    rectangle: Rectangle | None = None
    steps: tuple[str, ...] = field(default=(), compare=False)

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
                if args:
                    raise self.error("h-and-v takes no parameters", no)
                h_and_v = True
                steps.append("h-and-v")
            elif key == "connect":
                if connect is not None or rect is not None:
                    raise self.error("only one connect or findrectangle step is allowed", no)
                connect = self.connect(no, args)
                steps.append("connect")
            elif key == "findrectangle":
                if connect is not None or rect is not None:
                    raise self.error("only one connect or findrectangle step is allowed", no)
                if len(args) != 3:
                    raise self.error("findrectangle needs width, height and error %", no)
                w, h = self.ints(args[:2], no, "findrectangle", lo=1)
                (err,) = self.numbers(args[2:], no, "findrectangle error")
                if not 0 <= err < 100:
                    raise self.error("findrectangle error % must be in [0, 100)", no)
                rect = Rectangle(w, h, err)
                steps.append("findrectangle")
            else:
                raise self.error(f"unexpected {key!r} outside a segment", no)
        if not segments:
            raise self.error("a filter needs at least one beginsegment … endsegment", last_line)
        return Filter(self.name, tuple(segments), h_and_v, connect, rect, tuple(steps))

    def segment(self, start: int, args: list[str]) -> Segment:
        lo = hi = None
        if args:
            if len(args) != 2:
                raise self.error(
                    "beginsegment takes no parameters or min and max total length", start
                )
            lo, hi = self.ints(args, start, "beginsegment", lo=1)
            if lo > hi:
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
                if sum(s.min_len for s in subs) == 0:
                    raise self.error("a segment must match at least one tile", no)
                if seg.longest > MAX_SEGMENT_TILES:
                    raise self.error(f"a segment may span at most {MAX_SEGMENT_TILES} tiles", start)
                if lo is not None and lo > sum(s.max_len for s in subs):
                    raise self.error(
                        "beginsegment minimum exceeds what the subsegments can match", start
                    )
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
        lo, hi = self.ints(args, start, "beginsubsegment", lo=0)
        if hi < 1 or lo > hi:
            raise self.error(f"beginsubsegment: bad length range {lo}..{hi}", start)
        cats: list[CategorySpec] = []
        max_errors = 0
        while (item := self.next()) is not None:
            no, words = item
            key, rest = words[0], words[1:]
            if key == "endsubsegment":
                if not cats:
                    raise self.error("a subsegment needs at least one category", no)
                if max_errors >= hi and hi > 0:
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
        while (item := self.next()) is not None:
            no, words = item
            key, rest = words[0], words[1:]
            if key == "endcategory":
                return CategorySpec(negate=negate, **props)
            if key not in ("inclination", "state", "orientation"):
                raise self.error(f"unexpected {key!r} inside a category", no)
            if key in props:
                raise self.error(f"{key} given twice in one category", no)
            props[key] = self.values(no, key, rest)
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
        if key == "inclination":
            bad = [v for v in vals if v > 8]
            if bad:
                raise self.error(f"inclination must be 0–8, got {bad[0]}", no)
        elif key == "state":
            bad = [v for v in vals if v > 2]
            if bad:
                raise self.error(f"state must be 0, 1 or 2, got {bad[0]}", no)
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
        lims = self.ints(nums[:4], no, "connect", lo=-1)
        err = self.numbers(nums[4:], no, "connect maxerror")[0] if len(nums) == 5 else 0.0
        if not 0 <= err < 100:
            raise self.error("connect maxerror % must be in [0, 100)", no)
        lo_l, hi_l, lo_w, hi_w = (None if v == -1 else v for v in lims)
        for lo, hi, what in ((lo_l, hi_l, "length"), (lo_w, hi_w, "width")):
            if lo is not None and hi is not None and lo > hi:
                raise self.error(f"connect: min {what} exceeds max {what}", no)
        return Connect(method, lo_l, hi_l, lo_w, hi_w, err)


# --------------------------------------------------------------------------- writing and transforming


def format_filter(f: Filter) -> str:
    """The filter as text that parses back to an equal Filter."""
    out: list[str] = []
    for seg in f.segments:
        head = (
            "beginsegment"
            if seg.min_total is None
            else f"beginsegment {seg.min_total} {seg.max_total}"
        )
        out.append(head)
        if seg.invert:
            out.append("  invert")
        if seg.direction != "both":
            out.append(f"  {seg.direction}")
        for sub in seg.subsegments:
            out.append(
                f"  beginsubsegment {sub.min_len} {sub.max_len}"
                + (" exclude" if sub.exclude else "")
            )
            if sub.max_errors:
                out.append(f"    maxerrors {sub.max_errors}")
            for cat in sub.categories:
                out.append("    begincategory" + (" not" if cat.negate else ""))
                out.append(f"      inclination {cat.inclination.text()}")
                out.append(f"      state {cat.state.text()}")
                out.append(f"      orientation {cat.orientation.text()}")
                out.append("    endcategory")
            out.append("  endsubsegment")
        out.append("endsegment")
    for step in f.steps or _default_steps(f):
        if step == "h-and-v":
            out.append("h-and-v")
        elif step == "connect" and f.connect is not None:
            c = f.connect
            lims = " ".join(
                str(-1 if v is None else v)
                for v in (c.min_length, c.max_length, c.min_width, c.max_width)
            )
            tail = f" {c.max_error:g}" if c.method == "segment" and c.max_error else ""
            out.append(f"connect {c.method} {lims}{tail}")
        elif step == "findrectangle" and f.rectangle is not None:
            r = f.rectangle
            out.append(f"findrectangle {r.width} {r.height} {r.error:g}")
    return "\n".join(out) + "\n"


def _default_steps(f: Filter) -> tuple[str, ...]:
    steps = ["h-and-v"] if f.h_and_v else []
    if f.connect is not None:
        steps.append("connect")
    if f.rectangle is not None:
        steps.append("findrectangle")
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
                    state=c.state.map(state),
                    orientation=c.orientation.map(ori),
                )
                for c in sub.categories
            ),
        )
        for sub in seg.subsegments
    )
    return replace(seg, subsegments=subs, invert=False)
