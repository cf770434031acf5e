"""Accuracy of the refinement against the proving ground's truth: one table per scenario with
the start model, standard photoclinometry and PWM (RMS in m and GSD, median, NCC, SSIM, boulder
height ratio, runtime, peak memory), and a second with the height error by wavelength band and
where it lies (walls, rims, maplet edges, shadow, elsewhere: RMS in GSD).

    .venv/bin/python bench/accuracy.py [--scenarios tiny site site-hard site-polar] [--knowledge-error 1,1e-4]
                                       [--sims DIR ...] [--modes standard pwm] [--paths refine run]
                                       [--out DIR] [--workers 2]

--paths: `refine` runs `pwm refine` (no catalog); `run` runs `pwm run` into a fresh SQLite catalog
and evaluates its latest version, as operations make it (in PWM mode).

Simulations are reused when OUT/<scenario>/truth/manifest.json exists; --sims names existing
simulation directories (each with downlink/ and truth/), which are only read: their refined
models and evaluations go to OUT/<directory name>/. Each step runs in its own process so that its
peak memory is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from pwm.evaluate.classes import CLASSES

CHILD = """
import resource, sys
from service.cli import app
try:
    app(sys.argv[1:], prog_name="pwm", standalone_mode=False)
finally:
    # the largest process: the command itself or one of its worker processes
    peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    print("PEAK_KIB", peak, file=sys.stderr)
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
    peak_g = f"{peak:.2f}" if peak is not None else "-"
    return (f"{label:<10}{f('rms_m', '.3f'):>8}{f('rms_gsd', '.2f'):>8}{f('median_m', '.3f'):>9}{f('ncc', '.3f'):>7}"
            f"{f('ssim', '.3f'):>7}{f('boulder_height_ratio_median', '.2f'):>9}"
            f"{f('steep_boulder_height_ratio_median', '.2f'):>7}"
            f"{time_s:>8}{peak_g:>8}")


def split_row(label: str, figures: dict) -> str:
    """RMS by band and by class, in GSD."""
    gsd = figures["gsd_m"]
    cells = [f"{v / gsd:>11.2f}" for v in figures.get("bands_rms_m", {}).values()]
    classes = figures.get("classes_m", {})
    cells += [f"{classes[c]['rms'] / gsd:>13.2f}" if c in classes else f"{'-':>13}" for c in CLASSES]
    return f"{label:<12}" + "".join(cells)



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="*", default=None, help="simulate (or reuse) these scenarios under OUT")
    parser.add_argument("--sims", nargs="*", type=Path, default=[], help="existing simulation directories")
    parser.add_argument("--modes", nargs="+", default=["standard", "pwm"], choices=["standard", "pwm"])
    parser.add_argument("--paths", nargs="+", default=["refine"], choices=["refine", "run"],
                        help="pwm refine (standard and pwm modes), pwm run (pwm mode, through the catalog)")
    parser.add_argument("--knowledge-error", default=None, help="POS_M,POINT_RAD for the simulated kernels")
    parser.add_argument("--out", type=Path, default=Path("out/bench-accuracy"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--search-px", type=float, default=None,
                        help="pwm refine --search-px (default: 32 with --knowledge-error or a directory named *-ke, "
                             "else 1)")
    args = parser.parse_args()
    scenarios = args.scenarios if args.scenarios is not None else ([] if args.sims else ["tiny", "site", "site-polar"])
    runs = []
    for name in scenarios:
        sim = args.out / (name + (f"-ke{args.knowledge_error}" if args.knowledge_error else ""))
        if not (sim / "truth" / "manifest.json").exists():
            extra = ["--knowledge-error", args.knowledge_error] if args.knowledge_error else []
            pwm("simulate", str(sim), "--scenario", name, "--seed", "1", "--with-start-model", *extra)
        runs.append((sim, sim))
    runs += [(sim, args.out / sim.name) for sim in args.sims]
    for sim, work in runs:
        downlink, truth = sim / "downlink", sim / "truth"
        site_radius_km = json.loads((truth / "manifest.json").read_text())["scenario"]["site_size_km"] / 2
        search = args.search_px or (32.0 if args.knowledge_error or sim.name.endswith("-ke") else 1.0)
        lines, splits = [], []
        steps: list[tuple[str, Path, tuple[float, float] | None, Path | None]] = [
            ("start", downlink / "start_model.obj", None, None)]
        for mode in args.modes if "refine" in args.paths else []:
            out = work / f"refined-{mode}"
            seconds, peak = pwm("refine", str(downlink), "--start", str(downlink / "start_model.obj"),
                                "--out", str(out), "--mode", mode, "--workers", str(args.workers),
                                "--radius", str(1.3 * site_radius_km), "--search-px", str(search))
            steps.append((mode, out / "refined.ply", (seconds, peak), out / "maplets.json"))
        if "run" in args.paths:
            data = work / "run-data"
            env = {"PWM_DATA_DIR": str(data), "PWM_DATABASE_URL": "", "PWM_BROKER_URL": ""}
            if data.exists():
                subprocess.run(["rm", "-rf", str(data)], check=True)
            seconds, peak = pwm("run", str(downlink), "--workers", str(args.workers), "--mode", "pwm",
                                "--tile-radius", str(1.3 * site_radius_km), env=env)
            pwm("export", "latest", "--format", "ply", "--out", str(work / "run" / "refined.ply"), env=env)
            steps.append(("pwm run", work / "run" / "refined.ply", (seconds, peak), None))
        for label, model, cost, maplets in steps:
            report = work / f"evaluation-{label.replace(' ', '-')}.json"
            pwm("evaluate", str(model), "--truth", str(truth), "--json", str(report), "--plots",
                str(work / f"plots-{label.replace(' ', '-')}"), *(["--maplets", str(maplets)] if maplets else []))
            figures = json.loads(report.read_text())
            lines.append(row(label, figures, *(cost or (None, None))))
            splits.append((split_row(label, figures), list(figures.get("bands_rms_m", {}))))
        gsd = json.loads((truth / "manifest.json").read_text())["gsd_m"]
        print(f"\n{sim.name}: GSD {gsd:.3f} m")
        print(f"{'model':<10}{'RMS m':>8}{'RMS GSD':>8}{'median m':>9}{'NCC':>7}{'SSIM':>7}{'boulders':>9}{'steep':>7}"
              f"{'time s':>8}{'GiB':>8}")
        print("\n".join(lines), flush=True)
        print(f"\n{sim.name}: height error by wavelength band and by class, RMS in GSD")
        print(f"{'model':<12}" + "".join(f"{name:>11}" for name in splits[0][1])
              + "".join(f"{name:>13}" for name in CLASSES))
        print("\n".join(line for line, _ in splits), flush=True)


if __name__ == "__main__":
    main()
