"""The missions a simulated downlink can come from: what their labels call the mission, the
spacecraft, the camera and the target, which real kernels and shape they use, and the kernels
the simulator writes where the real ones are not bundled (a clock, the target's constants).

Only the simulator knows these: every command reading the downlink learns them from the labels
and the kernels.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pwm.io.spice_kernels import BUNDLED_DIR, write_sclk

SHAPES_DIR = BUNDLED_DIR.parent / "shapes"


@dataclass(frozen=True)
class Mission:
    """name, host, target_label: as the labels give them; instrument_label: the labels'
    instrument name (None: the name of the instrument's SPICE frame). kernels: bundled kernel
    (path under pwm/data/spice) -> folder of the downlink it goes in; shape: bundled base shape (km); spacecraft_frame:
    the frame the spacecraft attitude CK gives; write_kernels: writes the kernels the simulator
    makes up into a kernel directory, before the others are used, and returns their paths."""

    name: str
    host: str
    target_label: str
    instrument_label: str | None
    kernels: dict[str, str]
    shape: str
    spacecraft_frame: str
    write_kernels: Callable[[Path], list[Path]] | None = None


# Ryugu after Watanabe et al. 2019 (Science 364, 268): pole RA 96.4, Dec -66.4 deg (retrograde
# spin), period 7.63262 h; radii: the half extents of the bundled shape model (km).
RYUGU = 2162173
_CLOCK_ZERO_ET = 473342400.0  # 2015-01-01T00:00:00 TDB, before the launch: clock counts stay positive
_RYUGU_CONSTANTS = f"""KPL/PCK

Ryugu constants for simulated downlinks (pwm.simulate.missions), with its body-fixed frame.

\\begindata

BODY{RYUGU}_RADII = ( 0.5093 0.5096 0.4821 )
BODY{RYUGU}_POLE_RA = ( 96.4 0.0 0.0 )
BODY{RYUGU}_POLE_DEC = ( -66.4 0.0 0.0 )
BODY{RYUGU}_PM = ( 0.0 {360.0 * 24.0 / 7.63262:.6f} 0.0 )

FRAME_RYUGU_FIXED = {RYUGU}
FRAME_{RYUGU}_NAME = 'RYUGU_FIXED'
FRAME_{RYUGU}_CLASS = 2
FRAME_{RYUGU}_CLASS_ID = {RYUGU}
FRAME_{RYUGU}_CENTER = {RYUGU}
OBJECT_{RYUGU}_FRAME = 'RYUGU_FIXED'

\\begintext
"""


def _hayabusa2_kernels(kernel_dir: Path) -> list[Path]:
    """A clock for HAYABUSA2 (-37) and Ryugu's constants and frame."""
    sclk, pck = kernel_dir / "sclk" / "pwm_hyb2_sclk.tsc", kernel_dir / "pck" / "pwm_ryugu.tpc"
    for path in (sclk, pck):
        path.parent.mkdir(parents=True, exist_ok=True)
    write_sclk(sclk, spacecraft=-37, epoch_et=_CLOCK_ZERO_ET)
    pck.write_text(_RYUGU_CONSTANTS)
    return [sclk, pck]


MISSIONS: dict[str, Mission] = {
    "osiris-rex": Mission(
        name="OSIRIS-REx", host="OSIRIS-REX", target_label="Bennu", instrument_label=None,
        kernels={"naif0012.tls": "lsk", "bennu_v16.tpc": "pck", "orx_v14.tf": "fk",
                 "orx_ocams_v07.ti": "ik", "orx_sclkscet_00065.tsc": "sclk"},
        shape="bennu_radar_nolan2013_sbgat.obj", spacecraft_frame="ORX_SPACECRAFT"),
    "hayabusa2": Mission(
        name="Hayabusa2", host="HAYABUSA2", target_label="(162173) Ryugu", instrument_label="ONC-T",
        kernels={"naif0012.tls": "lsk", "hyb2/hyb2_v10.tf": "fk", "hyb2/hyb2_onc_v00.ti": "ik"},
        shape="ryugu_test.obj", spacecraft_frame="HAYABUSA2_SC_BUS_PRIME",
        write_kernels=_hayabusa2_kernels),
}
