"""Named proving-ground scenarios: the truth asteroid, the observation plan and the camera."""

from __future__ import annotations

from pydantic import BaseModel, Field

MAPCAM = -64361
ONC_T = -37100  # Hayabusa2's telescopic optical navigation camera


class Scenario(BaseModel):
    """Everything that defines a simulated campaign. Lengths in km unless named otherwise."""

    name: str
    description: str
    mission: str = Field("osiris-rex", description="a key of pwm.simulate.missions.MISSIONS: labels, kernels, shape")
    instrument_id: int = MAPCAM
    target: str = "BENNU"
    body_frame: str = "IAU_BENNU"
    start_utc: str = "2019-03-04T00:00:00"
    campaign_days: float = Field(10.0, description="span of the imaging campaign")
    subsolar_lat_deg: tuple[float, float] = Field((-4.0, 8.0), description="subsolar latitude at start and end")

    site_lat_deg: float
    site_lon_deg: float
    site_size_km: float
    gsd_km: float = Field(description="nadir image ground sample distance")
    truth_resolution_km: float
    base_edge_km: float = 0.004
    global_roughness_km: float = 0.0
    n_craters: int = 6
    n_boulders: int = 10
    steep_boulders: int = 3
    cobble_cover: float = Field(0.8, description="fraction of the site strewn with 0.3-3 m rocks")

    global_views: bool = Field(False, description="look at the whole body instead of a site")
    n_nadir: int = 6
    emissions_deg: tuple[float, ...] = (20.0, 32.0, 45.0)
    n_azimuths: int = 8
    incidences_deg: tuple[float, ...] = (20.0, 30.0, 40.0, 50.0, 60.0, 70.0)
    n_validation: int = 3
    pointing_scatter_km: float = Field(0.0, description="aim points scattered this far around the site centre")

    subframe_px: int | None = Field(None, description="read out a centred square detector window of this size")
    full_well_dn: float = 16383.0
    exposure_fill: float = Field(0.7, description="fraction of full scale the brightest expected pixel reaches")
    exposure_error: float = Field(0.03,
                                  description="1-sigma relative brightness error per image, unknown to processing")
    read_noise_dn: float = 2.0
    gain_e_per_dn: float = 4.0

    @property
    def n_images(self) -> int:
        return self.n_nadir + len(self.off_nadir_views())

    def off_nadir_views(self) -> list[tuple[float, float]]:
        """(emission, azimuth) pairs in degrees for the off-nadir images; azimuth from north, east positive."""
        return [(e, 360.0 * k / self.n_azimuths + 7.0 * j)
                for k in range(self.n_azimuths) for j, e in enumerate(self.emissions_deg)]


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in [
        Scenario(
            name="tiny",
            description="a 10 m site, 5 cm GSD, 6 images of 320x320 (detector windows): for tests (seconds)",
            site_lat_deg=10.0, site_lon_deg=40.0, site_size_km=0.010,
            gsd_km=5.0e-5, truth_resolution_km=1.25e-5, base_edge_km=0.008,
            n_craters=2, n_boulders=12, steep_boulders=5,
            n_nadir=2, emissions_deg=(30.0,), n_azimuths=4, incidences_deg=(35.0, 50.0, 60.0),
            n_validation=1, campaign_days=2.0, subframe_px=320,
        ),
        Scenario(
            name="ryugu-tiny",
            description="tiny's design on Ryugu with Hayabusa2's ONC-T (1024 px, 13 um pixels): a second mission",
            mission="hayabusa2", instrument_id=ONC_T, target="RYUGU", body_frame="RYUGU_FIXED",
            start_utc="2018-10-01T00:00:00",
            site_lat_deg=10.0, site_lon_deg=40.0, site_size_km=0.010,
            gsd_km=5.0e-5, truth_resolution_km=1.25e-5, base_edge_km=0.008,
            n_craters=2, n_boulders=12, steep_boulders=5,
            n_nadir=2, emissions_deg=(30.0,), n_azimuths=4, incidences_deg=(35.0, 50.0, 60.0),
            n_validation=1, campaign_days=2.0, subframe_px=320,
            # aim points off the site centre: a boresight through a vertex of the start model's
            # grid can slip between its single-precision triangles (Embree) and meet the far side
            pointing_scatter_km=0.001,
        ),
        Scenario(
            name="site",
            description="a 50 m candidate sampling site at mid latitude, 10 cm GSD, 30+ images",
            site_lat_deg=12.0, site_lon_deg=60.0, site_size_km=0.05,
            gsd_km=1.0e-4, truth_resolution_km=2.5e-5, n_boulders=100, steep_boulders=25,
            pointing_scatter_km=0.008,
        ),
        Scenario(
            name="site-polar",
            description="the same site design at high latitude: long shadows",
            site_lat_deg=62.0, site_lon_deg=200.0, site_size_km=0.05,
            gsd_km=1.0e-4, truth_resolution_km=2.5e-5,
            n_boulders=100, steep_boulders=25, incidences_deg=(55.0, 60.0, 65.0, 70.0, 75.0),
            pointing_scatter_km=0.008,
        ),
        Scenario(
            name="global-coarse",
            description="the whole body at 2 m GSD, for tiling and photogrammetry",
            site_lat_deg=12.0, site_lon_deg=60.0, site_size_km=0.05,
            gsd_km=2.0e-3, truth_resolution_km=1.0e-4, base_edge_km=5.0e-4, global_roughness_km=5.0e-4,
            global_views=True, n_nadir=0, emissions_deg=(0.0,), n_azimuths=36,
            incidences_deg=(30.0, 45.0, 60.0), n_validation=4, campaign_days=5.0,
        ),
    ]
}


def get_scenario(name: str) -> Scenario:
    """The scenario called `name`; ValueError listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}") from None
