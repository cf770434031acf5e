"""Accuracy of the refinement against the proving ground's truth: one table per downlink with
the start model, standard photoclinometry and PWM (RMS in m and GSD, median, coverage of a
global model, NCC, SSIM, boulder height ratio, the least of the largest boulders' and the share
of the squared error beyond 3 GSD, runtime, peak memory), and a second with the
height error by wavelength band and where it lies (walls, rims, maplet edges, shadow,
elsewhere: RMS in GSD).

    .venv/bin/python bench/accuracy.py [--scenarios tiny site site-hard site-polar castalia-tiny campaign-eros]
                                       [--knowledge-error 1,1e-4 | nav:3,1,50,20] [--sims DIR ...]
                                       [--modes standard pwm] [--paths refine run] [--out DIR] [--workers 2]

--scenarios: scenarios or campaigns (pwm simulate --scenario); a campaign's downlinks are taken in
time order. --paths: `refine` runs `pwm refine` (no catalog) where the downlink brings a start
model; `run` runs `pwm run` into a fresh SQLite catalog (one per campaign, each downlink after
the last) and evaluates its latest version, as operations make it (in PWM mode). A site is
refined and judged about its disc; a survey over the whole body, judged with --scope global.

Simulations are reused when their truth is there (OUT/<name>/truth/manifest.json, or a campaign's
truth/campaign.json); --sims names existing simulation directories (each with downlink/ and
truth/, or a campaign's downlinks/ and truth/), which are only read: their refined models and
evaluations go to OUT/<directory name>/. Each step runs in its own process so that its peak
memory is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from pwm.evaluate.classes import CLASSES

CHILD = """
import resource, sys
from service.cli import app
try:
    # without standalone mode a command's exit status is returned, not raised
    code = app(sys.argv[1:], prog_name="pwm", standalone_mode=False)
finally:
    # the largest process: the command itself or one of its worker processes
    peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    print("PEAK_KIB", peak, file=sys.stderr)
sys.exit(code if isinstance(code, int) else 0)
"""


def pwm(*args: str, env: dict[str, str] | None = None) -> tuple[float, float]:
    """Run a pwm command (with `env` added to the environment); its wall time (s) and peak memory (GiB)."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})})
    if done.returncode != 0:
        raise RuntimeError(f"pwm {' '.join(args)} failed:\n{done.stderr[-4000:]}")
    peak = next(int(line.split()[1]) for line in done.stderr.splitlines() if line.startswith("PEAK_KIB"))
    return time.perf_counter() - start, peak / 2**20


def row(label: str, figures: dict, seconds: float | None, peak: float | None) -> str:
    def f(key: str, fmt: str) -> str:
        value = figures.get(key)
        return format(value, fmt) if value is not None else "-"

    time_s = f"{seconds:.0f}" if seconds is not None else "-"
    tail = f"{figures['tail']['squared_error_share']:.2f}" if "tail" in figures else "-"
    peak_g = f"{peak:.2f}" if peak is not None else "-"
    return (f"{label:<10}{f('rms_m', '.3f'):>8}{f('rms_gsd', '.2f'):>8}{f('median_m', '.3f'):>9}"
            f"{f('completeness', '.3f'):>9}{f('ncc', '.3f'):>7}"
            f"{f('ssim', '.3f'):>7}{f('boulder_height_ratio_median', '.2f'):>9}"
            f"{f('steep_boulder_height_ratio_median', '.2f'):>7}{f('largest_boulder_height_ratio_min', '.2f'):>8}"
            f"{tail:>7}{time_s:>8}{peak_g:>8}")


def split_row(label: str, figures: dict) -> str:
    """RMS by band and by class, in GSD."""
    gsd = figures["gsd_m"]
    cells = [f"{v / gsd:>11.2f}" for v in figures.get("bands_rms_m", {}).values()]
    classes = figures.get("classes_m", {})
    cells += [f"{classes[c]['rms'] / gsd:>13.2f}" if c in classes else f"{'-':>13}" for c in CLASSES]
    return f"{label:<12}" + "".join(cells)


@dataclass(frozen=True)
class Run:
    """One downlink to refine and judge: its simulation directory, downlink and truth, where its
    models and evaluations go, and the catalog `pwm run` adds it to (a campaign shares one)."""

    name: str
    sim: Path
    downlink: Path
    truth: Path
    work: Path
    catalog: Path


def downlinks(sim: Path, work: Path) -> list[Run]:
    """The downlinks of a simulation directory: its one, or a campaign's in time order."""
    summary = sim / "truth" / "campaign.json"
    if not summary.exists():
        return [Run(sim.name, sim, sim / "downlink", sim / "truth", work, work / "run-data")]
    return [Run(f"{sim.name}/{entry['name']}", sim, sim / entry["downlink"], sim / entry["truth"],
                work / entry["name"], work / "run-data")
            for entry in json.loads(summary.read_text())["downlinks"]]


def exported(run: Run, env: dict[str, str], *, site: bool) -> Path:
    """The latest version as one PLY: the whole mesh, or for a site the tile of a version stored
    in tiles (PWM_MESH_TILE_FACES) that holds the site's origin farthest inside its box."""
    whole = run.work / "run" / "refined.ply"
    whole.unlink(missing_ok=True)
    folder = run.work / "run" / "tiles"
    try:
        pwm("export", "latest", "--format", "ply", "--out", str(whole), env=env)
        return whole
    except RuntimeError:
        if not site:
            raise
        # here, so that a failure other than a tiled version's is told with the first one's
        pwm("export", "latest", "--format", "ply", "--tile", "all", "--out", str(folder), env=env)
    origin = json.loads((run.truth / "truth.json").read_text())["origin_km"]
    tiles = json.loads((folder / "tiles.json").read_text())["tiles"]

    def inside_by(tile: dict) -> float:
        low, high = tile["box_km"]
        return min(min(o - a, b - o) for o, a, b in zip(origin, low, high, strict=True))

    return folder / max(tiles, key=inside_by)["file"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="*", default=None,
                        help="simulate (or reuse) these scenarios or campaigns under OUT")
    parser.add_argument("--sims", nargs="*", type=Path, default=[], help="existing simulation directories")
    parser.add_argument("--modes", nargs="+", default=["standard", "pwm"], choices=["standard", "pwm"])
    parser.add_argument("--paths", nargs="+", default=["refine"], choices=["refine", "run"],
                        help="pwm refine (standard and pwm modes), pwm run (pwm mode, through the catalog)")
    parser.add_argument("--knowledge-error", default=None,
                        help="the simulated kernels' errors: POS_M,POINT_RAD or nav:ALONG_M,CROSS_M,MISALIGN_URAD,"
                             "DRIFT_URAD (pwm simulate --knowledge-error)")
    parser.add_argument("--out", type=Path, default=Path("out/bench-accuracy"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--search-px", type=float, default=None,
                        help="pwm refine --search-px (default: 32 with --knowledge-error or a directory named *-ke, "
                             "else 1)")
    args = parser.parse_args()
    scenarios = args.scenarios if args.scenarios is not None else ([] if args.sims else ["tiny", "site", "site-polar"])
    runs: list[Run] = []
    for name in scenarios:
        sim = args.out / (name + (f"-ke{args.knowledge_error}" if args.knowledge_error else ""))
        if not any((sim / "truth" / f).exists() for f in ("manifest.json", "campaign.json")):
            extra = ["--knowledge-error", args.knowledge_error] if args.knowledge_error else []
            pwm("simulate", str(sim), "--scenario", name, "--seed", "1", "--with-start-model", *extra)
        runs += downlinks(sim, sim)
    for sim in args.sims:
        runs += downlinks(sim, args.out / sim.name)
    fresh: set[Path] = set()
    for run in runs:
        manifest = json.loads((run.truth / "manifest.json").read_text())
        scenario = manifest["scenario"]
        # a site is refined about its disc; a survey wherever the commands find the images look
        region = [] if scenario["global_views"] else [str(1.3 * scenario["site_size_km"] / 2)]
        search = args.search_px or (32.0 if args.knowledge_error or run.sim.name.endswith("-ke") else 1.0)
        lines, splits = [], []
        start = run.downlink / "start_model.obj"
        steps: list[tuple[str, Path, tuple[float, float] | None, Path | None]] = (
            [("start", start, None, None)] if start.exists() else [])
        for mode in args.modes if "refine" in args.paths and start.exists() else []:
            out = run.work / f"refined-{mode}"
            seconds, peak = pwm("refine", str(run.downlink), "--start", str(start), "--out", str(out), "--mode", mode,
                                "--workers", str(args.workers), *(["--radius-km", *region] if region else []),
                                "--search-px", str(search))
            steps.append((mode, out / "refined.ply", (seconds, peak), out / "maplets.json"))
        if "run" in args.paths:
            env = {"PWM_DATA_DIR": str(run.catalog), "PWM_DATABASE_URL": "", "PWM_BROKER_URL": ""}
            if run.catalog not in fresh and run.catalog.exists():
                subprocess.run(["rm", "-rf", str(run.catalog)], check=True)
            fresh.add(run.catalog)
            seconds, peak = pwm("run", str(run.downlink), "--workers", str(args.workers), "--mode", "pwm",
                                *(["--tile-radius-km", *region] if region else []), env=env)
            steps.append(("pwm run", exported(run, env, site=not scenario["global_views"]), (seconds, peak), None))
        for label, model, cost, maplets in steps:
            report = run.work / f"evaluation-{label.replace(' ', '-')}.json"
            pwm("evaluate", str(model), "--truth", str(run.truth), "--json", str(report), "--plots",
                str(run.work / f"plots-{label.replace(' ', '-')}"), *(["--maplets", str(maplets)] if maplets else []))
            figures = json.loads(report.read_text())
            lines.append(row(label, figures, *(cost or (None, None))))
            splits.append((split_row(label, figures), list(figures.get("bands_rms_m", {}))))
        print(f"\n{run.name}: GSD {manifest['gsd_m']:.3f} m, {manifest['image_count']} images")
        print(f"{'model':<10}{'RMS m':>8}{'RMS GSD':>8}{'median m':>9}{'coverage':>9}{'NCC':>7}{'SSIM':>7}"
              f"{'boulders':>9}{'steep':>7}{'largest':>8}{'>3GSD':>7}{'time s':>8}{'GiB':>8}")
        print("\n".join(lines), flush=True)
        if not any(bands for _, bands in splits):  # a survey's: no site heights to split
            continue
        print(f"\n{run.name}: height error by wavelength band and by class, RMS in GSD")
        print(f"{'model':<12}" + "".join(f"{name:>11}" for name in splits[0][1])
              + "".join(f"{name:>13}" for name in CLASSES))
        print("\n".join(line for line, _ in splits), flush=True)

if __name__ == "__main__":
    main()
