"""Ingest a hostile downlink: the simulated `tiny` downlink with one crafted file (or pair) of
every class issues 17 and 44 list, and others; print where each file of it ended up in the
catalog, with the reason, and the ingest's time and peak memory. Exit status 1 when a file is not
accounted for, a good image lost its geometry, a product that arrived broken and then whole is
not accepted, or the peak passes 1 GiB.

Transfers (issue 44) take two ingests: before the first, some products arrive broken (a label
without its data file, a data file cut short, a byte flipped against the manifest); before the
second, they arrive whole, and must then be accepted.

    .venv/bin/python bench/hostile_ingest.py [--sim DIR] [--work DIR]

--sim: the output of `pwm simulate DIR --scenario tiny --seed 3` (simulated, in a child
process, when missing: about 35 s). The batch and its SQLite catalog go to --work (default a
temporary directory). Peak memory is this process's maximum resident set (getrusage): the
ingest's, the simulation being another process.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
from sqlalchemy import select  # noqa: E402

from service.db import make_engine, make_sessionmaker, upgrade  # noqa: E402
from service.ingest import ingest_directory  # noqa: E402
from service.rows import DownlinkFile, GeometryStatus, Image, ImageStatus, Kernel  # noqa: E402
from service.settings import IngestLimits  # noqa: E402

PEAK_LIMIT_BYTES = 1024**3
_LID = re.compile(r"<logical_identifier>([^<]+)<")


class Batch:
    """Hostile files written into a copy of a good downlink, each with what it tries."""

    def __init__(self, root: Path, outside: Path) -> None:
        self.root, self.outside = root, outside
        self.images = root / "images"
        self.template = sorted(self.images.glob("*.xml"))[0]
        self.tries: dict[str, str] = {}

    def clone(self, name: str, tries: str, *edits: tuple[str, str], data: bytes | None = None
              ) -> tuple[Path, Path]:
        """A copy of the first product as images/NAME.xml and NAME.fits (its own LID), edited."""
        label, fits = self.images / f"{name}.xml", self.images / f"{name}.fits"
        text = self.template.read_text()
        lid = _LID.search(text)[1]  # type: ignore[index]
        text = text.replace(f"<logical_identifier>{lid}<", f"<logical_identifier>{lid}_{name}<")
        text = text.replace(self.template.with_suffix(".fits").name, fits.name)
        for old, new in edits:
            if old not in text and not old.startswith("re:"):
                raise ValueError(f"{name}: {old!r} not in the label")
            text = re.sub(old[3:], new, text) if old.startswith("re:") else text.replace(old, new)
        label.write_text(text)
        if data is None:
            shutil.copy(self.template.with_suffix(".fits"), fits)
        else:
            fits.write_bytes(data)
        self.tries[label.name] = tries
        return label, fits

    def file(self, relative: str, tries: str, content: bytes | str = b"") -> Path:
        path = self.root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content.encode() if isinstance(content, str) else content)
        self.tries[path.name] = tries
        return path

    def link(self, relative: str, target: Path, tries: str) -> None:
        path = self.root / relative
        path.symlink_to(target)
        self.tries[path.name] = tries


def _card(fits: bytes, card: str, value: str) -> bytes:
    """`fits` with the value of one header card replaced."""
    start = fits.index(card.ljust(8).encode() + b"= ")
    return fits[:start + 10] + value.rjust(20).encode() + fits[start + 30:]


def _fits(cards: list[tuple[str, str]], data: bytes, *, pad_to: int = 0) -> bytes:
    """A FITS file: the header cards (value strings as FITS writes them), END, padding to 2880
    bytes (or to pad_to), then the data, padded too."""
    text = "".join(f"{k:<8}= {v:>20}".ljust(80) for k, v in cards) + "END".ljust(80)
    header = text.encode("ascii")
    header += b" " * (max(pad_to, -len(header) % 2880 + len(header)) - len(header))
    return header + data + b"\0" * (-len(data) % 2880)


def _array_edits(*, offset: int | None = None, data_type: str | None = None,
                 size: int | None = None) -> list[tuple[str, str]]:
    """Label edits of the Array_2D_Image's offset and data type, and of the file's size."""
    edits = [("re:<md5_checksum>[^<]+</md5_checksum>", "")]
    if offset is not None:
        edits.append(("re:(<Array_2D_Image>\\s*<offset[^>]*>)\\d+<", f"\\g<1>{offset}<"))
    if data_type is not None:
        edits.append(("re:<data_type>[^<]+<", f"<data_type>{data_type}<"))
    if size is not None:
        edits.append(("re:<file_size[^>]*>\\d+<", f'<file_size unit="byte">{size}<'))
    return edits


def build_issue44(batch: Batch, fits: bytes) -> None:
    """The classes of issue 44 that one ingest judges: kernels that would poison the pool,
    arrays their labels misdescribe, bounds a label or header controls, duplicate elements."""
    kernels = batch.root / "kernels"
    spk = sorted((kernels / "spk").glob("*.bsp"))[0].read_bytes()
    batch.file("kernels/spk/zz_truncated.bsp", "an SPK cut after its summaries (DAFBEGGTEND later)",
               spk[:len(spk) * 3 // 5])
    radii = re.compile(r"BODY(\d+)_RADII\s*=\s*\([^)]*\)")
    pck = next(p for p in (kernels / "pck").glob("*.tpc") if radii.search(p.read_text()))
    body = radii.search(pck.read_text())[1]  # type: ignore[index]
    batch.file("kernels/pck/zz_string_radii.tpc", "a PCK giving the body's radii as strings",
               f"KPL/PCK\n\\begindata\nBODY{body}_RADII = ( 'a' 'b' 'c' )\n\\begintext\n")
    batch.file("kernels/pck/zz_zero_radii.tpc", "a PCK giving the body radii of zero",
               f"KPL/PCK\n\\begindata\nBODY{body}_RADII = ( 0.0 0.0 0.0 )\n\\begintext\n")
    lsk = next((kernels / "lsk").glob("*.tls")).read_text()
    batch.file("kernels/lsk/zz_shifted.tls", "an LSK moving DELTET/DELTA_T_A by an hour",
               re.sub(r"DELTET/DELTA_T_A\s*=\s*32.184", "DELTET/DELTA_T_A = 3632.184", lsk))
    header, array = fits[:2880], fits[2880:]
    batch.clone("lsb_over_msb", "SignedLSB2 over a big-endian array (pixels byte-swapped)",
                *_array_edits(data_type="SignedLSB2"))
    batch.clone("offset_in_header", "the array's offset inside the header (header read as pixels)",
                *_array_edits(offset=1440))
    batch.clone("offset_plus_2", "the array's offset two bytes past the data start (one pixel)",
                *_array_edits(offset=2882))
    batch.clone("bscale_lie", "FITS BSCALE 1.0 against the label's scaling_factor",
                *_array_edits(), data=_card(fits, "BSCALE", "1.0"))
    side = 320
    for name, value in (("all_inf", np.inf), ("all_nan", np.nan)):
        data = _fits([("SIMPLE", "T"), ("BITPIX", "-32"), ("NAXIS", "2"), ("NAXIS1", str(side)),
                      ("NAXIS2", str(side))], np.full((side, side), value, ">f4").tobytes())
        batch.clone(name, f"an array of {value} (IEEE754MSBSingle)", *_array_edits(
            data_type="IEEE754MSBSingle", size=len(data)), ("re:<scaling_factor>[^<]+<",
                                                            "<scaling_factor>1.0<"), data=data)
    batch.clone("complex", "a complex data type (ComplexMSB8) over the array",
                *_array_edits(data_type="ComplexMSB8"))
    batch.clone("constant_range", "a missing_constant outside SignedMSB2's range",
                *_array_edits(), ("re:<missing_constant>[^<]+<", "<missing_constant>-99999<"))
    big = 17 * 10**6 // 2880 * 2880
    cards = [line.decode() for line in (header[i:i + 80] for i in range(0, 2880, 80))]
    head = "".join(c for c in cards if not c.startswith("END") and c.strip())
    head += ("COMMENT " + "x" * 72) * ((big - len(head)) // 80 - 1) + "END".ljust(80)
    head_bytes = head.encode("ascii").ljust(big)
    batch.clone("header_17mb", "a 17 MB FITS header (read whole: 7x its size in memory)",
                *_array_edits(offset=big, size=big + len(array)),
                ("re:(<Header>\\s*<offset[^<]+</offset>\\s*<object_length[^>]*>)\\d+<",
                 f"\\g<1>{big}<"), data=head_bytes + array)
    files = "<File><file_name>same_file_50k.fits</file_name></File>" * 50_000
    batch.clone("same_file_50k", "a label naming its data file 50,000 times (hashed each time)",
                ("<File_Area_Observational>", f"<File_Area_Observational>{files}"))
    batch.clone("duplicate_lid", "two logical_identifier elements (first wins silently)",
                ("re:(<logical_identifier>[^<]+</logical_identifier>)",
                 "\\1<logical_identifier>urn:nasa:pds:other:x</logical_identifier>"))
    batch.clone("duplicate_start", "two start_date_time elements (first wins silently)",
                ("re:(<start_date_time>[^<]+</start_date_time>)",
                 "\\1<start_date_time>2020-01-01T00:00:00Z</start_date_time>"))
    batch.clone("leap_second", "a start in a leap second (PDS4 allows 23:59:60)",
                ("re:<start_date_time>[^<]+<", "<start_date_time>2016-12-31T23:59:60.500Z<"),
                ("re:<stop_date_time>[^<]+<", "<stop_date_time>2017-01-01T00:00:00.500Z<"))


class Transfers:
    """Products that arrive broken before the first ingest and whole before the second."""

    def __init__(self, batch: Batch, good: Path) -> None:
        self.whole: dict[Path, bytes] = {}
        late, _ = batch.clone("late_data", "its label before its data file (moved in later)")
        cut, _ = batch.clone("cut_short", "its data file cut short (re-transferred later)")
        # a good product, not the template, whose LIDVID zz_duplicate_lidvid takes meanwhile
        flipped_label = good
        self.labels = [late, cut, flipped_label]
        for label, broken in ((late, None), (cut, 0.5), (flipped_label, -1.0)):
            data = label.with_suffix(".fits")
            self.whole[data] = data.read_bytes()
            if broken is None:
                data.unlink()
            elif broken > 0:
                data.write_bytes(self.whole[data][:int(len(self.whole[data]) * broken)])
            else:  # one byte flipped: the manifest's and the label's checksums disagree
                flipped = bytearray(self.whole[data])
                flipped[-100] ^= 0xFF
                data.write_bytes(bytes(flipped))
        batch.tries[flipped_label.name] = "its data file a byte off the manifest, then whole"

    def deliver(self) -> None:
        for data, content in self.whole.items():
            data.write_bytes(content)


def build(batch: Batch) -> None:
    fits = batch.template.with_suffix(".fits").read_bytes()
    # 1. one bad label never stops the downlink
    batch.clone("exposure_text", "exposure_duration not a number",
                ("re:(<img:exposure_duration[^>]*>)[^<]+<", r"\1fast<"))
    batch.clone("header_1e20", "Header object_length 1e20 (OverflowError)",
                ("re:(<Header>\\s*<offset[^<]+</offset>\\s*<object_length[^>]*>)\\d+<",
                 r"\g<1>100000000000000000000<"))
    batch.clone("header_4e15", "Header object_length 4e15 (MemoryError)",
                ("re:(<Header>\\s*<offset[^<]+</offset>\\s*<object_length[^>]*>)\\d+<",
                 r"\g<1>4000000000000000<"))
    lid = _LID.search(batch.template.read_text())[1]  # type: ignore[index]
    for name, new_lid, vid in (("join_a", f"{lid}_j::1", "0"), ("join_b", f"{lid}_j", "1::0")):
        batch.clone(name, "two LIDs joining into one LIDVID (IntegrityError)",
                    ("re:<logical_identifier>[^<]+<", f"<logical_identifier>{new_lid}<"),
                    ("re:<version_id>[^<]+<", f"<version_id>{vid}<"))
    batch.clone("long_vid", "a 42-character version_id (VARCHAR(32))",
                ("re:<version_id>[^<]+<", f"<version_id>{'1' * 40}.0<"))
    batch.clone("zz_duplicate_lidvid", "the first product's LIDVID with other content",
                ("re:<logical_identifier>[^<]+<", f"<logical_identifier>{lid}<"),
                ("re:<md5_checksum>[^<]+</md5_checksum>", ""),
                data=fits[:-1] + bytes([fits[-1] ^ 1]))
    # 2. kernels only from the downlink
    pck = batch.outside / "bennu_big.tpc"
    pck.write_text("KPL/PCK\n\\begindata\nBODY2101955_RADII = ( 1.0 1.0 1.0 )\n\\begintext\n")
    batch.file("kernels/mk/outside.tm", "a meta-kernel naming a PCK outside ('..') and /etc/passwd",
               "KPL/MK\n\\begindata\nKERNELS_TO_LOAD = ( '../../../outside/bennu_big.tpc'\n"
               "'/etc/passwd' )\n\\begintext\n")
    # 3. the kernel pool
    batch.file("kernels/mk/giant.tm", "a meta-kernel of 200k entries (KERNELPOOLFULL)",
               "KPL/MK\n\\begindata\nKERNELS_TO_LOAD = (\n"
               + "".join(f"'k{i}.bsp'\n" for i in range(200_000)) + ")\n\\begintext\n")
    batch.file("kernels/pck/aaa_full.tpc", "a PCK of 20k strings, more than the pool holds",
               "KPL/PCK\n\\begindata\nFILLER = (\n"
               + "".join(f"'v{i}'\n" for i in range(20_000)) + ")\n\\begintext\n")
    # 6. label reading bounded
    batch.clone("giant_label", "a 16 MB label", ("<Identification_Area>",
                "<Identification_Area><!--" + "x" * 16 * 1024**2 + "-->"))
    for name, side in (("sparse_8000", 8000), ("beyond_detector", 4096)):
        size = 2880 + side * side * 2
        header = _card(_card(fits[:2880], "NAXIS1", str(side)), "NAXIS2", str(side))
        label, data = batch.clone(name, f"a sparse {side}x{side} array ({size / 1e6:.0f} MB)",
                                  ("re:<elements>\\d+<", f"<elements>{side}<"),
                                  ("re:<file_size[^>]*>\\d+<", f'<file_size unit="byte">{size}<'),
                                  ("re:<md5_checksum>[^<]+</md5_checksum>", ""), data=header)
        with open(data, "r+b") as fh:
            fh.truncate(size)
    # 7. symbolic links out of the downlink
    passwd_label, passwd = batch.clone("to_passwd", "its data file a link to /etc/passwd")
    passwd.unlink()
    passwd.symlink_to("/etc/passwd")
    shutil.copy(batch.template, batch.outside / "elsewhere.xml")
    batch.link("images/linked_label.xml", batch.outside / "elsewhere.xml", "a label linked outside")
    batch.link("kernels/linked.tpc", pck, "a kernel linked outside")
    batch.link("linked_dir", Path("/etc"), "a directory linked to /etc")
    # 9. lenient values
    for name, value in (("scale_nan", "NaN"), ("scale_inf", "inf"), ("scale_zero", "0.0")):
        batch.clone(name, f"scaling_factor {value}",
                    ("re:<scaling_factor>[^<]+<", f"<scaling_factor>{value}<"))
    for name, card, value in (("bitpix_lie", "BITPIX", "32"), ("naxis_lie", "NAXIS", "3")):
        batch.clone(name, f"FITS {card} {value}, the label otherwise",
                    ("re:<md5_checksum>[^<]+</md5_checksum>", ""), data=_card(fits, card, value))
    batch.clone("year_0019", "a year 0019 (SPICE reads 2019)",
                ("re:<start_date_time>\\d{4}", "<start_date_time>0019"),
                ("re:<stop_date_time>\\d{4}", "<stop_date_time>0019"))
    # and others
    batch.clone("traversal", "file_name ../../../etc/passwd",
                ("re:<file_name>[^<]+<", "<file_name>../../../etc/passwd<"))
    batch.clone("xxe", "an external entity naming /etc/passwd",
                ('<?xml version="1.0" encoding="UTF-8"?>',
                 '<?xml version="1.0" encoding="UTF-8"?>\n<!DOCTYPE p [<!ENTITY x SYSTEM '
                 '"file:///etc/passwd">]>'), ("re:<title>[^<]+<", "<title>&x;<"))
    laughs = '<!ENTITY l0 "lol">' + "".join(f'<!ENTITY l{i} "' + f"&l{i - 1};" * 10 + '">'
                                            for i in range(1, 10))
    batch.clone("laughs", "entity expansion (a billion laughs)",
                ('<?xml version="1.0" encoding="UTF-8"?>',
                 f'<?xml version="1.0" encoding="UTF-8"?>\n<!DOCTYPE p [{laughs}]>'),
                ("re:<title>[^<]+<", "<title>&l9;<"))
    batch.clone("truncated", "a FITS file cut in half", data=fits[:len(fits) // 2])
    batch.clone("malformed", "XML cut short", ("</Product_Observational>", ""))
    batch.file("images/zero.xml", "a zero-byte label")
    batch.clone("zero_data", "a zero-byte data file", ("re:<md5_checksum>[^<]+</md5_checksum>", ""),
                data=b"")
    batch.file("images/not_pds4.xml", "XML that is no PDS4 product", "<project><name>x</name></project>")
    batch.file("README.txt", "a file of no known type", "notes\n")
    batch.file("images/empty.bin", "a zero-byte file of no known type")
    batch.file("kernels/fake.bsp", "a .bsp that is not a kernel", "not a DAF")
    os.mkfifo(batch.root / "pipe")
    batch.tries["pipe"] = "a named pipe"
    build_issue44(batch, fits)


def account(sessions, root: Path) -> list[tuple[str, str, str]]:  # type: ignore[no-untyped-def]
    """(file, where the catalog has it, why) for every file, link and pipe under root."""
    with sessions() as session:
        kernels = {k.path: (f"kernel {k.status}", k.rejection_reason or "")
                   for k in session.scalars(select(Kernel))}
        labels, data = {}, {}
        for image in session.scalars(select(Image)):
            labels[image.label_path] = (f"image {image.status} {image.rejection_code or ''}".strip(),
                                        image.rejection_reason or image.geometry_unavailable_reason or "")
            data[image.data_path] = (f"data of {Path(image.label_path).name} ({image.status})", "")
        unused = {f.path: (f"unused {f.code}", f.reason) for f in session.scalars(select(DownlinkFile))}
    rows = []
    for path in sorted(root.rglob("*")):
        if path.is_dir() and not path.is_symlink():
            continue
        key = str(path)
        where, why = (unused.get(key) or kernels.get(key) or labels.get(key) or data.get(key)
                      or (("delivery file", "") if path.name in ("manifest.json", "start_model.obj")
                          else ("UNACCOUNTED", "")))
        rows.append((str(path.relative_to(root)), where, why))
    return rows


def named_outside(sessions, root: Path) -> list[tuple[str, str, str]]:  # type: ignore[no-untyped-def]
    """The files outside the batch its meta-kernels name, as the catalog refused them."""
    with sessions() as session:
        return [(f.path, f"unused {f.code}", f.reason) for f in session.scalars(select(DownlinkFile))
                if not Path(f.path).is_relative_to(root)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim", type=Path, default=None)
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="pwm-hostile-"))
    sim = args.sim or work / "sim"
    if not (sim / "downlink").is_dir():
        subprocess.run([sys.executable, "-c", "from service.cli import app; app()", "simulate", str(sim),
                        "--scenario", "tiny", "--seed", "3", "--with-start-model"], check=True, env={**os.environ,
                                                                                "PYTHONPATH": str(REPO)})
    root, outside = work / "hostile", work / "outside"
    shutil.rmtree(root, ignore_errors=True)
    shutil.rmtree(outside, ignore_errors=True)
    shutil.copytree(sim / "downlink", root)
    outside.mkdir()
    batch = Batch(root, outside)
    good = sorted(p.name for p in batch.images.glob("*.xml"))
    build(batch)
    transfers = Transfers(batch, batch.images / good[-1])
    url = f"sqlite:///{work / 'catalog.sqlite'}"
    (work / "catalog.sqlite").unlink(missing_ok=True)
    upgrade(url)
    sessions = make_sessionmaker(make_engine(url))
    clock = time.perf_counter()
    report = ingest_directory(sessions, root, limits=IngestLimits())
    elapsed = time.perf_counter() - clock
    transfers.deliver()
    again = ingest_directory(sessions, root, limits=IngestLimits())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    rows = account(sessions, root)
    width = max(len(r[0]) for r in rows)
    print(f"{'file':<{width}}  {'in the catalog':<32}  why (what it tries)")
    for name, where, why in rows:
        tries = batch.tries.get(Path(name).name)
        print(f"{name:<{width}}  {where:<32}  {why[:110]}" + (f"  ({tries})" if tries else ""))
    missing = [r for r in rows if r[1] == "UNACCOUNTED"]
    print(f"\n{len(rows)} files, {len(missing)} unaccounted; {report.summary()}")
    for name, where, why in named_outside(sessions, root):
        print(f"{name:<{width}}  {where:<32}  {why[:110]}")
    print(f"re-run: {again.summary()}")
    for failure in again.failures:
        print(f"  re-run failure {failure.path}: {failure.code}: {failure.reason[:100]}")
    lost = without_geometry(sessions, [batch.images / n for n in good]
                            + [label for label in transfers.labels if label.name not in good])
    for name in lost:
        print(f"NOT ACCEPTED WITH GEOMETRY after the re-run: {name}")
    print(f"ingest {elapsed:.1f} s; peak memory (max RSS) {peak / 1024**2:.0f} MiB")
    return 1 if missing or lost or peak >= PEAK_LIMIT_BYTES or again.failed else 0


def without_geometry(sessions, labels: list[Path]) -> list[str]:  # type: ignore[no-untyped-def]
    """The good and the re-delivered products that are not accepted with geometry: the hostile
    files must harm none of them, and a whole delivery must replace a broken one."""
    with sessions() as session:
        done = {image.label_path for image in session.scalars(select(Image).where(
            Image.status == ImageStatus.ACCEPTED, Image.geometry_status == GeometryStatus.COMPUTED))}
    return [label.name for label in labels if str(label) not in done]


if __name__ == "__main__":
    sys.exit(main())
