"""Named proving-ground scenarios: the truth asteroid, the observation plan and the camera; and
campaigns, sequences of downlinks of one truth asteroid."""

from __future__ import annotations

from datetime import datetime, timedelta

from pydantic import BaseModel, Field, field_validator, model_validator

from pwm.photometry import PHOTOMETRY
from pwm.simulate.lidar import LidarSpec
from pwm.simulate.missions import MISSIONS
from pwm.simulate.optics import Optics

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
    large_boulders: int = Field(0, ge=0, description="boulders 3-5 m across and about 1 m tall, each the largest "
                                                     "within a maplet's side (pwm.simulate.terrain.add_large_boulders)")

    global_views: bool = Field(False, description="look at the whole body instead of a site")
    survey_latitudes_deg: tuple[float, ...] = Field(
        (), description="global views as an approach takes them (pwm.simulate.plan.plan_approach): the whole body "
                        "in frame, every longitude twice, at sub-spacecraft latitudes cycling through these; "
                        "none: views placed about the Sun (plan_global)")
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

    # How far the proving ground departs from what the solver assumes (none by default).
    photometry: str = Field("mcewen", description="the truth's reflectance law: a key of pwm.photometry.PHOTOMETRY")
    supersample: int = Field(1, ge=1, le=4, description="rays per pixel along each axis, averaged")
    optics: Optics = Field(default_factory=Optics, description="blur, smear and flat-field residual of the camera")
    start_error_rms_gsd: float = Field(0.0, ge=0.0, le=20.0,
                                       description="RMS of smooth undulations added to the start model, in GSD")
    start_error_band_m: tuple[float, float] = Field((10.0, 40.0),
                                                    description="shortest and longest wavelength of those, m")
    lidar: LidarSpec | None = Field(None, description="a laser altimeter ranging through the views' windows")

    @field_validator("photometry")
    @classmethod
    def _known_photometry(cls, name: str) -> str:
        if name not in PHOTOMETRY:
            raise ValueError(f"unknown photometry {name!r}; choose one of {', '.join(PHOTOMETRY)}")
        return name

    @model_validator(mode="after")
    def _ordered_band(self) -> Scenario:
        shortest, longest = self.start_error_band_m
        if not 0 < shortest < longest:
            raise ValueError(f"start_error_band_m must be 0 < shortest < longest, not {self.start_error_band_m}")
        return self

    @model_validator(mode="after")
    def _approach_of_a_known_body(self) -> Scenario:
        if self.survey_latitudes_deg and not self.global_views:
            raise ValueError("survey_latitudes_deg plans global views: set global_views")
        if any(abs(lat) >= 80.0 for lat in self.survey_latitudes_deg):
            raise ValueError("survey latitudes must lie within 80 deg of the equator (the views keep north up)")
        if self.mission not in MISSIONS:
            raise ValueError(f"unknown mission {self.mission!r}; choose one of {', '.join(MISSIONS)}")
        body = MISSIONS[self.mission].body
        if body is not None and (self.target, self.body_frame) != (body.name, body.frame):
            raise ValueError(f"mission {self.mission} writes the kernels of {body.name} in {body.frame}, "
                             f"not of {self.target} in {self.body_frame}")
        return self

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
            description="a 50 m candidate sampling site at mid latitude, 10 cm GSD, 30+ images, and lidar "
                        "profiles through each view's window",
            site_lat_deg=12.0, site_lon_deg=60.0, site_size_km=0.05,
            gsd_km=1.0e-4, truth_resolution_km=2.5e-5, n_boulders=100, steep_boulders=25, large_boulders=4,
            pointing_scatter_km=0.008,
            # profiles as NEAR's or Hayabusa's lidar took them, the body turning beneath
            lidar=LidarSpec(pattern="profile", shots_per_view=200),
        ),
        Scenario(
            name="site-hard",
            description="site's design with what the solver does not assume: Hapke photometry with roughness and "
                        "an opposition surge, 2x2 sub-pixel sampling, blur, smear, a flat-field residual, and a "
                        "start model with 1 GSD RMS of 10-40 m undulations",
            site_lat_deg=12.0, site_lon_deg=60.0, site_size_km=0.05,
            gsd_km=1.0e-4, truth_resolution_km=2.5e-5, n_boulders=100, steep_boulders=25, large_boulders=4,
            pointing_scatter_km=0.008,
            photometry="hapke", supersample=2,
            optics=Optics(psf_sigma_px=0.6, smear_px=0.8, flat_field_rms=0.01),
            start_error_rms_gsd=1.0, start_error_band_m=(10.0, 40.0),
            lidar=LidarSpec(pattern="profile", shots_per_view=200),
        ),
        Scenario(
            name="site-polar",
            description="the same site design at high latitude: long shadows",
            site_lat_deg=62.0, site_lon_deg=200.0, site_size_km=0.05,
            gsd_km=1.0e-4, truth_resolution_km=2.5e-5,
            n_boulders=100, steep_boulders=25, large_boulders=4, incidences_deg=(55.0, 60.0, 65.0, 70.0, 75.0),
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
        Scenario(
            name="global-tiny",
            description="global-coarse's design for tests, seconds: 12 images of the whole body at 4 m GSD "
                        "through a 320 px detector window, over a coarse truth; and an OLA-like lidar's rasters "
                        "over the body, one per view",
            site_lat_deg=12.0, site_lon_deg=60.0, site_size_km=0.05,
            gsd_km=4.0e-3, truth_resolution_km=1.0e-4, base_edge_km=2.0e-3, global_roughness_km=1.0e-3,
            global_views=True, n_nadir=0, emissions_deg=(0.0,), n_azimuths=12, subframe_px=320,
            incidences_deg=(30.0, 50.0), n_validation=1, campaign_days=5.0,
            lidar=LidarSpec(pattern="raster", shots_per_view=400),
        ),
        # Bodies far from their ellipsoid (issue 45), surveyed as an approach would: the PCK's
        # ellipsoid (the shape's half extents) misses their surface by many survey GSDs.
        Scenario(
            name="castalia-survey",
            description="an approach survey of a contact binary: Castalia's radar shape at a third of its size "
                        "(0.54 km long, Bennu's length, so Bennu's landforms and survey costs carry over), 36 "
                        "MapCam images of 1024 px with the whole body in frame at 1.5 m GSD (about 360 px long), "
                        "every longitude twice, latitudes -45 to +45, phase 20-70 deg; a 0.54 m truth with 0.5 m "
                        "roughness",
            mission="osiris-rex-castalia", target="CASTALIA", body_frame="CASTALIA_FIXED",
            site_lat_deg=10.0, site_lon_deg=20.0, site_size_km=0.05,
            gsd_km=1.5e-3, truth_resolution_km=1.0e-4, base_edge_km=6.0e-4, global_roughness_km=5.0e-4,
            global_views=True, survey_latitudes_deg=(-45.0, -15.0, 15.0, 45.0), n_nadir=0, emissions_deg=(0.0,),
            n_azimuths=36, incidences_deg=(20.0, 30.0, 40.0, 50.0, 60.0, 70.0), n_validation=4,
            campaign_days=10.0,
        ),
        Scenario(
            name="castalia-tiny",
            description="castalia-survey's design for tests, seconds: 12 images of the whole body at 2.5 m GSD "
                        "through a 320 px detector window, over a coarse truth (2.2 m)",
            mission="osiris-rex-castalia", target="CASTALIA", body_frame="CASTALIA_FIXED",
            site_lat_deg=10.0, site_lon_deg=20.0, site_size_km=0.05,
            gsd_km=2.5e-3, truth_resolution_km=2.5e-4, base_edge_km=2.5e-3, global_roughness_km=1.0e-3,
            global_views=True, survey_latitudes_deg=(-45.0, -15.0, 15.0, 45.0), n_nadir=0, emissions_deg=(0.0,),
            n_azimuths=12, subframe_px=320, incidences_deg=(20.0, 45.0, 70.0), n_validation=1, campaign_days=5.0,
        ),
        Scenario(
            name="eros-survey",
            description="an approach survey of an elongated body with a saddle: Eros's SPC shape at a twentieth of "
                        "its size (1.63 km long: the GSD stays in metres, whole in MapCam's frame), 36 images of "
                        "1024 px at 3.5 m GSD (about 470 px long), every longitude twice, latitudes -45 to +45, "
                        "phase 20-70 deg; a 1.3 m truth with 1 m roughness",
            mission="osiris-rex-eros", target="EROS", body_frame="EROS_FIXED",
            site_lat_deg=10.0, site_lon_deg=90.0, site_size_km=0.1,
            gsd_km=3.5e-3, truth_resolution_km=2.0e-4, base_edge_km=1.3e-3, global_roughness_km=1.0e-3,
            global_views=True, survey_latitudes_deg=(-45.0, -15.0, 15.0, 45.0), n_nadir=0, emissions_deg=(0.0,),
            n_azimuths=36, incidences_deg=(20.0, 30.0, 40.0, 50.0, 60.0, 70.0), n_validation=4,
            campaign_days=10.0,
        ),
        Scenario(
            name="eros-tiny",
            description="eros-survey's design for tests, seconds: 12 images of the whole body at 7 m GSD through a "
                        "320 px detector window, over a coarse truth (5.1 m)",
            mission="osiris-rex-eros", target="EROS", body_frame="EROS_FIXED",
            site_lat_deg=10.0, site_lon_deg=90.0, site_size_km=0.1,
            gsd_km=7.0e-3, truth_resolution_km=5.0e-4, base_edge_km=6.0e-3, global_roughness_km=2.0e-3,
            global_views=True, survey_latitudes_deg=(-45.0, -15.0, 15.0, 45.0), n_nadir=0, emissions_deg=(0.0,),
            n_azimuths=12, subframe_px=320, incidences_deg=(20.0, 45.0, 70.0), n_validation=1, campaign_days=5.0,
        ),
    ]
}


class Campaign(BaseModel):
    """A mission's sequence of downlinks over one truth asteroid: a global survey, then sites.

    The body (its base, roughness and the landforms over it) is the survey's; each site keeps its
    own design (place, size, truth resolution, images) from its scenario. Lengths in m here, as
    landform sizes are spoken of.
    """

    name: str
    description: str
    survey: Scenario
    sites: tuple[Scenario, ...]
    craters: int = Field(description="craters placed over the whole body")
    crater_diameter_m: tuple[float, float]
    boulders: int = Field(description="boulders placed over the whole body, clear of the sites")
    steep_boulders: int
    boulder_diameter_m: tuple[float, float]

    @model_validator(mode="after")
    def _one_body_in_time_order(self) -> Campaign:
        if not self.survey.global_views or any(s.global_views for s in self.sites):
            raise ValueError("a campaign is one global survey followed by site downlinks")
        for s in self.sites:
            if (s.mission, s.target, s.body_frame) != (self.survey.mission, self.survey.target, self.survey.body_frame):
                raise ValueError(f"site {s.name} is not of the survey's mission and body")
        # a downlink's kernels span a day before its first image to two after its last
        downlinks = (self.survey, *self.sites)
        for before, after in zip(downlinks, downlinks[1:], strict=False):
            end = datetime.fromisoformat(before.start_utc) + timedelta(days=before.campaign_days + 2)
            if datetime.fromisoformat(after.start_utc) - timedelta(days=1) <= end:
                raise ValueError(f"{after.name} starts before the kernels of {before.name} end")
        if len({s.name for s in downlinks}) != len(downlinks):
            raise ValueError("the downlinks' scenarios need distinct names (they name products and kernels)")
        return self

    @property
    def downlinks(self) -> list[Scenario]:
        """The scenarios of the downlinks in time order."""
        return [self.survey, *self.sites]


def _campaign_part(scenario: str, **changes: object) -> Scenario:
    return Scenario.model_validate({**SCENARIOS[scenario].model_dump(), **changes})


CAMPAIGNS: dict[str, Campaign] = {
    c.name: c
    for c in [
        Campaign(
            name="campaign",
            description="global-coarse's survey, at twice its images (72), of a Bennu with craters and boulders "
                        "everywhere (2 m GSD, a 0.5 m truth), then site's and site-polar's reconnaissance (10 cm GSD, "
                        "each pixel the mean of 3 x 3 rays) at two places of it; an OLA-like lidar's rasters through "
                        "the survey's views, and profiles through the first site's",
            # 36 images left 63% of the surface seen by fewer than five within SPC's 40 deg emission
            # rule: too few for the five-view set (bench/RESULTS.md); surveys take many more
            survey=_campaign_part("global-coarse", name="campaign-survey", n_azimuths=72,
                                  lidar=LidarSpec(pattern="raster", shots_per_view=2000)),
            # the sites' pixels integrate over their footprint as a detector's do: one ray per 10 cm
            # pixel over a 2.5 cm truth aliases the cobbles' slopes into the images (bench/RESULTS.md)
            sites=(_campaign_part("site", name="campaign-site-a", start_utc="2019-03-14T00:00:00", supersample=3),
                   _campaign_part("site-polar", name="campaign-site-b", start_utc="2019-03-28T00:00:00",
                                  supersample=3)),
            craters=30, crater_diameter_m=(10.0, 80.0), boulders=60, steep_boulders=15,
            boulder_diameter_m=(6.0, 30.0),
        ),
        Campaign(
            name="campaign-tiny",
            description="campaign's design for tests, seconds: global-tiny's survey (4 m GSD, 12 images) of a body "
                        "with 20-60 m craters and 12-30 m boulders, then two tiny sites (5 cm GSD, 6 images each, "
                        "each pixel the mean of 2 x 2 rays)",
            # no lidar yet: the catalog reads no lidar products (issue 46's next step)
            survey=_campaign_part("global-tiny", name="campaign-tiny-survey", lidar=None),
            sites=(_campaign_part("tiny", name="campaign-tiny-site-a", start_utc="2019-03-14T00:00:00",
                                  supersample=2),
                   _campaign_part("tiny", name="campaign-tiny-site-b", start_utc="2019-03-20T00:00:00",
                                  site_lat_deg=-30.0, site_lon_deg=200.0, supersample=2)),
            craters=6, crater_diameter_m=(20.0, 60.0), boulders=8, steep_boulders=2, boulder_diameter_m=(12.0, 30.0),
        ),
        Campaign(
            name="campaign-castalia",
            description="castalia-survey (36 images, 1.5 m GSD) of a Castalia with the Bennu campaign's craters and "
                        "boulders at Bennu's density (20 craters of 10-80 m, 40 boulders of 6-30 m), then site's "
                        "reconnaissance (10 cm GSD) on the end of a lobe",
            survey=_campaign_part("castalia-survey", name="campaign-castalia-survey"),
            sites=(_campaign_part("site", name="campaign-castalia-site", mission="osiris-rex-castalia",
                                  target="CASTALIA", body_frame="CASTALIA_FIXED", start_utc="2019-03-20T00:00:00",
                                  site_lat_deg=10.0, site_lon_deg=20.0),),
            craters=20, crater_diameter_m=(10.0, 80.0), boulders=40, steep_boulders=10,
            boulder_diameter_m=(6.0, 30.0),
        ),
        Campaign(
            name="campaign-eros",
            description="eros-survey (36 images, 3.5 m GSD) of an Eros with craters and boulders at the Bennu "
                        "campaign's density and sizes in survey GSD (35 craters of 18-140 m, 70 boulders of "
                        "10-50 m), then site's reconnaissance (10 cm GSD) on the flank of the long axis",
            survey=_campaign_part("eros-survey", name="campaign-eros-survey"),
            sites=(_campaign_part("site", name="campaign-eros-site", mission="osiris-rex-eros", target="EROS",
                                  body_frame="EROS_FIXED", start_utc="2019-03-20T00:00:00", site_lat_deg=10.0,
                                  site_lon_deg=90.0),),
            craters=35, crater_diameter_m=(18.0, 140.0), boulders=70, steep_boulders=18,
            boulder_diameter_m=(10.0, 50.0),
        ),
    ]
}


def get_scenario(name: str) -> Scenario:
    """The scenario called `name`; ValueError listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}") from None
