"""What a downlink's PDS4 image labels say, resolved against the loaded SPICE kernel pool: the
observer (spacecraft), the instrument, the target and its body-fixed frame, and the exposure
times.

The one home of these rules: the catalog's ingest (service.ingest) and the downlink reader
(pwm.io.downlink) both use them, so that an image is the same instrument's, target's and
epoch's on both paths. Labels name things as people write them ('MapCam' on 'OSIRIS-REx',
'AMICA' on 'HAYABUSA', '(101955) Bennu'); kernels as NAIF does (ORX_OCAMS_MAPCAM, OSIRIS-REX,
HAYABUSA_AMICA, BENNU). Nothing here knows a mission: only the labels and the kernels do.
"""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

import spiceypy as sp

from pwm.io.pds4 import ImageLabel, ProductError
from pwm.io.spice_geometry import spacecraft_of
from pwm.io.spice_kernels import spice_message

# SPICE errors that mean "no data for that time" rather than a broken kernel set.
COVERAGE_ERRORS = frozenset({"SPICE(SPKINSUFFDATA)", "SPICE(NOFRAMECONNECT)"})
_FOV_ROOM = 10_000  # pool names one lookup of the instruments' FOV keywords may return


LABEL_SUFFIXES = frozenset({".xml", ".cub"})
"""PDS4 labels, and ISIS cubes (which carry their label, pwm.io.isis)."""


def find_labels(directory: Path) -> list[Path]:
    """The labelled products under `directory` (LABEL_SUFFIXES, any case), in path order."""
    return [p for p in sorted(Path(directory).rglob("*")) if p.suffix.lower() in LABEL_SUFFIXES and p.is_file()]


def name_variants(name: str) -> list[str]:
    """Names SPICE may know a label's name by: as given, upper case, spaces and hyphens as
    underscores; '(101955) Bennu' also as 'BENNU' and '101955 BENNU'."""
    upper = " ".join(name.split()).upper()
    numbered = re.fullmatch(r"\((\d+)\)\s*(.+)", upper)
    forms = [name.strip(), upper, re.sub(r"[\s\-]+", "_", upper)]
    if numbered:
        forms += [numbered[2], f"{numbered[1]} {numbered[2]}", re.sub(r"[\s\-]+", "_",
                                                                       numbered[2])]
    return list(dict.fromkeys(forms))


def body_code(names: list[str]) -> int | None:
    """The NAIF id of the first of `names` the pool knows (bodn2c), None if none."""
    with sp.no_found_check():
        for name in names:
            code, found = sp.bodn2c(name)
            if found:
                return int(code)
    return None


def observer_code(host_name: str | None) -> int | None:
    """The NAIF id of a label's host (the spacecraft), None without a host or if SPICE does not
    know it."""
    return body_code(name_variants(host_name)) if host_name and host_name.strip() else None


def instrument_code(product: ImageLabel, observer: int) -> int | None:
    """The NAIF id of the product's instrument on `observer`: bodn2c of the label's (or FITS
    INSTRUME) name in its variants, bare or prefixed with the host's, else the one instrument
    of that spacecraft whose kernel-pool name ends in _<name>."""
    names = [n for n in (product.instrument_name, (product.fits_header or {}).get("INSTRUME"))
             if isinstance(n, str) and n.strip()]
    variants = [v for n in names for v in name_variants(n)]
    hosts = name_variants(product.host_name) if product.host_name else []
    candidates = variants + [f"{h}_{v}" for h in hosts for v in variants]

    def on_observer(code: int) -> bool:
        return code <= -1000 and spacecraft_of(code) == observer

    with sp.no_found_check():
        for name in candidates:
            code, found = sp.bodn2c(name)
            if found and on_observer(int(code)):
                return int(code)
    suffixes = {"_" + v for v in variants}
    matches = {code for code, name in _pool_bodies()
               if on_observer(code) and any(name.upper().endswith(s) for s in suffixes)}
    return matches.pop() if len(matches) == 1 else None


def _pool_bodies() -> list[tuple[int, str]]:
    """(NAIF id, name) of every body name the loaded text kernels define (NAIF_BODY_NAME)."""
    with sp.no_found_check():
        count, _, defined = sp.dtpool("NAIF_BODY_NAME")
    if not defined:
        return []
    names = sp.gcpool("NAIF_BODY_NAME", 0, count)
    codes = sp.gipool("NAIF_BODY_CODE", 0, count)
    return [(int(c), n) for n, c in zip(names, codes, strict=True)]


def target_frame(name: str | None) -> tuple[int | None, str | None]:
    """The NAIF id of a label's target and its body-fixed frame: (None, None) when SPICE does
    not know the body, (id, None) when no frame is associated with it (cidfrm)."""
    code = body_code(name_variants(name)) if name and name.strip() else None
    return (None, None) if code is None else (code, frame_of(code))


def frame_of(code: int) -> str | None:
    """The body-fixed frame the kernels associate with body `code` (cidfrm), None if none."""
    with sp.no_found_check():
        _, frame, found = sp.cidfrm(code)
    return frame if found else None


def body_name(code: int) -> str:
    """SPICE's name of a body, or its id as text when it has none."""
    with sp.no_found_check():
        name, found = sp.bodc2n(code)
    return name if found else str(code)


def known_instruments() -> list[tuple[int, str]]:
    """(NAIF id, name) of the instruments the pool's kernels give a field of view, by id."""
    with sp.no_found_check():
        keys, found = sp.gnpool("INS-*_FOV_SHAPE", 0, _FOV_ROOM)
    codes = sorted({int(m[1]) for k in (keys if found else [])
                    if (m := re.fullmatch(r"INS(-\d+)_FOV_SHAPE", k))})
    return [(code, body_name(code)) for code in codes]


def instrument_named(name: str) -> int:
    """The NAIF id of an instrument given by a person (a NAIF id, or a name in any of its
    variants); ValueError listing the instruments the kernels define otherwise."""
    text = name.strip()
    code = int(text) if re.fullmatch(r"-?\d+", text) else body_code(name_variants(text))
    if code is None or code > -1000:
        defined = ", ".join(f"{n} ({c})" for c, n in known_instruments()) or "none"
        raise ValueError(f"instrument {name!r} is not a NAIF instrument name or id the kernels "
                         f"know; they define {defined}")
    return code


# SPICE reads years 0 to 99 as abbreviations (0019 as 2019) and Python as written: a time this
# early is refused, so that the catalog's UTC and its ET never disagree.
FIRST_YEAR = 1000
# A leap second, which PDS4 allows: the 61st second of a day's last minute.
_LEAP_SECOND = re.compile(r"(.+T23:59:)60(\.\d*)?")


def parse_utc(stamp: str) -> datetime:
    """A PDS4 date_time (calendar or day-of-year form, UTC) as an aware datetime; ProductError
    (bad_time) otherwise, and for a year before FIRST_YEAR. A time in a leap second (23:59:60.x),
    which a datetime cannot hold, is the first instant of the next day (as
    service.kernels.et_to_datetime gives it); exposure_et has its exact ET."""
    text = stamp.strip().removesuffix("Z")
    leap = _LEAP_SECOND.fullmatch(text)
    if leap:
        text = leap[1] + "59"
    try:
        if re.fullmatch(r"\d{4}-\d{3}T.*", text):
            parsed = datetime.strptime(text, "%Y-%jT%H:%M:%S.%f" if "." in text
                                       else "%Y-%jT%H:%M:%S")
        else:
            parsed = datetime.fromisoformat(text)
    except ValueError as exc:
        raise ProductError("bad_time", f"time {stamp!r} is not a PDS4 UTC date_time") from exc
    if parsed.utcoffset():
        raise ProductError("bad_time", f"time {stamp!r} is not UTC")
    if parsed.year < FIRST_YEAR:
        raise ProductError("bad_time", f"time {stamp!r}: year {parsed.year} is before "
                           f"{FIRST_YEAR} (SPICE would read {parsed.year:04d} as an abbreviated year)")
    if leap:
        parsed += timedelta(seconds=1)
    return parsed.replace(tzinfo=UTC)


def exposure_times(product: ImageLabel) -> tuple[datetime, datetime]:
    """Start and stop of the exposure (UTC); ProductError (bad_time) when unreadable or when
    the stop precedes the start."""
    start, stop = parse_utc(product.start_utc), parse_utc(product.stop_utc)
    if stop < start:
        raise ProductError("bad_time", f"stop {product.stop_utc} precedes start {product.start_utc}")
    return start, stop


def exposure_et(product: ImageLabel) -> tuple[float, float]:
    """Start and stop of the exposure, ET s, from the pool's leapseconds kernel; ProductError
    (bad_time) when parse_utc refuses them, SPICE cannot read them, one is in a leap second the
    kernel does not have (SPICE would read it as the next day's first second) or the stop
    precedes the start (within one leap second, which exposure_times cannot tell)."""
    start, stop = (_et(stamp) for stamp in (product.start_utc, product.stop_utc))
    if stop < start:
        raise ProductError("bad_time", f"stop {product.stop_utc} precedes start {product.start_utc}")
    return start, stop


def _et(stamp: str) -> float:
    after = parse_utc(stamp)
    try:
        if _LEAP_SECOND.fullmatch(stamp.strip().removesuffix("Z")) and not _leap_second_before(after):
            raise ProductError("bad_time", f"time {stamp!r}: the leapseconds kernel has no leap "
                               f"second at the end of {(after - timedelta(days=1)).date()}")
        return sp.str2et(stamp)
    except sp.utils.exceptions.SpiceyError as exc:
        raise ProductError("bad_time", spice_message(exc)) from exc


def _leap_second_before(midnight: datetime) -> bool:
    """Whether the minute before `midnight` UTC has 61 seconds in the pool's leapseconds
    kernel: two seconds of ET, not one, from its 23:59:59 to midnight."""
    stamps = (midnight - timedelta(seconds=1), midnight)
    before, at = (sp.str2et(s.strftime("%Y-%m-%dT%H:%M:%S")) for s in stamps)
    return at - before > 1.5
