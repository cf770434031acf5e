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

import numpy as np

from pwm.io.meshio import read_obj
from pwm.io.spice_kernels import BUNDLED_DIR, write_sclk
from pwm.mesh import Mesh

SHAPES_DIR = BUNDLED_DIR.parent / "shapes"


@dataclass(frozen=True)
class Body:
    """A target whose constants and body-fixed frame the simulator writes (a text PCK): its
    NAIF id and name (defined in the kernel, as SPICE may not know the body), its frame's name,
    the IAU rotation model (pole RA and Dec, prime meridian at J2000 and spin, deg and deg/day)
    and where those values come from."""

    code: int
    name: str
    frame: str
    pole_ra_deg: float
    pole_dec_deg: float
    prime_meridian_deg: float
    spin_deg_per_day: float
    source: str

    def pck(self, radii_km: tuple[float, float, float]) -> str:
        """The text PCK of the body with these triaxial radii (km)."""
        c = self.code
        return f"""KPL/PCK

{self.name} constants for simulated downlinks (pwm.simulate.missions), with its body-fixed frame.
{self.source}

\\begindata

NAIF_BODY_NAME += ( '{self.name}' )
NAIF_BODY_CODE += ( {c} )

BODY{c}_RADII = ( {radii_km[0]:.6f} {radii_km[1]:.6f} {radii_km[2]:.6f} )
BODY{c}_POLE_RA = ( {self.pole_ra_deg} 0.0 0.0 )
BODY{c}_POLE_DEC = ( {self.pole_dec_deg} 0.0 0.0 )
BODY{c}_PM = ( {self.prime_meridian_deg} {self.spin_deg_per_day:.6f} 0.0 )

FRAME_{self.frame} = {c}
FRAME_{c}_NAME = '{self.frame}'
FRAME_{c}_CLASS = 2
FRAME_{c}_CLASS_ID = {c}
FRAME_{c}_CENTER = {c}
OBJECT_{c}_FRAME = '{self.frame}'

\\begintext
"""


@dataclass(frozen=True)
class Mission:
    """name, host, target_label: as the labels give them; instrument_label: the labels'
    instrument name (None: the name of the instrument's SPICE frame). kernels: bundled kernel
    (path under pwm/data/spice) -> folder of the downlink it goes in; shape: bundled base shape (km); spacecraft_frame:
    the frame the spacecraft attitude CK gives; write_kernels: writes the kernels the simulator
    makes up into a kernel directory, before the others are used, and returns their paths.
    body: a target whose constants the simulator writes (`Body`), its radii the half extents of
    the base shape; scale: the factor from the bundled shape to the truth body's base (the one
    home of a body's size in the proving ground)."""

    name: str
    host: str
    target_label: str
    instrument_label: str | None
    kernels: dict[str, str]
    shape: str
    spacecraft_frame: str
    write_kernels: Callable[[Path], list[Path]] | None = None
    body: Body | None = None
    scale: float = 1.0

    def base_shape(self) -> Mesh:
        """The bundled shape times `scale`: the truth body's base, km."""
        shape = read_obj(SHAPES_DIR / self.shape)
        return Mesh(shape.vertices * self.scale, shape.faces, shape.albedo)

    def made_up_kernels(self, kernel_dir: Path) -> list[Path]:
        """Write the kernels the simulator makes up for this mission into kernel_dir (write_kernels',
        and the body's constants and frame); their paths."""
        paths = [] if self.write_kernels is None else self.write_kernels(kernel_dir)
        if self.body is not None:
            pck = kernel_dir / "pck" / f"pwm_{self.body.frame.lower()}.tpc"
            pck.parent.mkdir(parents=True, exist_ok=True)
            pck.write_text(self.body.pck(half_extents(self.base_shape())))
            paths.append(pck)
        return paths


def half_extents(mesh: Mesh) -> tuple[float, float, float]:
    """Half the extent along each axis of the vertices the faces use (km): the triaxial ellipsoid
    a PCK gives for a shape, its size and nothing of its form."""
    used = mesh.vertices[np.unique(mesh.faces)]
    a, b, c = (used.max(axis=0) - used.min(axis=0)) / 2
    return float(a), float(b), float(c)


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


CASTALIA = Body(code=2004769, name="CASTALIA", frame="CASTALIA_FIXED", pole_ra_deg=100.0, pole_dec_deg=70.0,
                prime_meridian_deg=0.0, spin_deg_per_day=360.0 * 24.0 / 4.07,
                source="Period 4.07 h (Hudson & Ostro 1994, Science 263, 940). The pole is the simulation's own:\n"
                       "the rotation about the shape's shortest principal axis (z) is what matters here.")
EROS = Body(code=2000433, name="EROS", frame="EROS_FIXED", pole_ra_deg=11.35, pole_dec_deg=17.22,
            prime_meridian_deg=326.07, spin_deg_per_day=1639.38864745,
            source="Rotation model of NAIF's pck00010.tpc (IAU 2009), about the SPC shape's z axis.")

_ORX_KERNELS = {"naif0012.tls": "lsk", "bennu_v16.tpc": "pck", "orx_v14.tf": "fk", "orx_ocams_v07.ti": "ik",
                "orx_sclkscet_00065.tsc": "sclk"}
# OSIRIS-REx's spacecraft and MapCam at another body: its kernels but Bennu's constants
_ORX_CAMERA = {name: kind for name, kind in _ORX_KERNELS.items() if kind != "pck"}

MISSIONS: dict[str, Mission] = {
    "osiris-rex": Mission(
        name="OSIRIS-REx", host="OSIRIS-REX", target_label="Bennu", instrument_label=None, kernels=_ORX_KERNELS,
        shape="bennu_radar_nolan2013_sbgat.obj", spacecraft_frame="ORX_SPACECRAFT"),
    # Castalia at a third of its size (0.54 km long, Bennu's length): the Bennu campaign's
    # landforms, roughness and survey cost carry over (issue 45's contact binary was 0.54 km too)
    "osiris-rex-castalia": Mission(
        name="OSIRIS-REx", host="OSIRIS-REX", target_label="(4769) Castalia", instrument_label=None,
        kernels=_ORX_CAMERA, shape="castalia_radar_hudson1994.obj", spacecraft_frame="ORX_SPACECRAFT",
        body=CASTALIA, scale=1.0 / 3.0),
    # Eros at a twentieth of its size (1.63 km long): whole in MapCam's frame at a few metres
    # GSD, the scale the proving ground's roughness, landforms and maplets are made for; the real
    # body (33 km) whole in the frame would be seen at 35 m
    "osiris-rex-eros": Mission(
        name="OSIRIS-REx", host="OSIRIS-REX", target_label="(433) Eros", instrument_label=None,
        kernels=_ORX_CAMERA, shape="eros_gaskell_q64_20k.obj", spacecraft_frame="ORX_SPACECRAFT",
        body=EROS, scale=0.05),
    "hayabusa2": Mission(
        name="Hayabusa2", host="HAYABUSA2", target_label="(162173) Ryugu", instrument_label="ONC-T",
        kernels={"naif0012.tls": "lsk", "hyb2/hyb2_v10.tf": "fk", "hyb2/hyb2_onc_v00.ti": "ik"},
        shape="ryugu_test.obj", spacecraft_frame="HAYABUSA2_SC_BUS_PRIME",
        write_kernels=_hayabusa2_kernels),
}
