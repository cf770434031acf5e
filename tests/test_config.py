"""The refinement configuration: its checks, and which settings its digest names."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import importlib.util
import numbers
import re
from pathlib import Path

import pytest

from pwm.alignment import Registration
from pwm.config import DEFAULTS, MODES, Placement, RefinementConfig
from pwm.photoclinometry import Solver
from pwm.weights import Rules


def test_modes_are_the_solver_modes():
    assert MODES == ("pwm", "standard")


@pytest.mark.parametrize("change, message", [
    ({"mode": "fast"}, "mode 'fast'"), ({"nodes": 4}, "at least 8"), ({"overlap": 0.9}, "overlap"),
    ({"spacing_gsd": 3.0}, "spacing"), ({"passes": 0}, "one pass"), ({"search_px": -1.0}, "non-negative"),
    ({"min_images": 0}, "at least one image"), ({"tile_radius_km": 0.0}, "positive"),
    ({"shape_window_nodes": 4}, "shape windows of 4 nodes"),
])
def test_a_bad_setting_is_refused_with_its_name(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(DEFAULTS, **change)


def test_the_digest_follows_what_changes_one_maplets_refinement():
    base = DEFAULTS.digest()
    assert RefinementConfig().digest() == base
    for change in ({"mode": "standard"}, {"search_px": 8.0}, {"min_images": 4}, {"shape_window_nodes": 0},
                   {"solver": Solver(slope_scale=0.2)}, {"rules": Rules(max_shadow_fraction=0.2)}):
        assert dataclasses.replace(DEFAULTS, **change).digest() != base, change
    # tiling makes other maplets, whose grids are in their own input hashes
    for change in ({"nodes": 64}, {"overlap": 0.5}, {"spacing_gsd": 0.5}, {"passes": 3}, {"tile_radius_km": 1.0}):
        assert dataclasses.replace(DEFAULTS, **change).digest() == base, change


def test_the_new_settings_are_checked():
    with pytest.raises(ValueError, match="knowledge sigmas"):
        dataclasses.replace(DEFAULTS, knowledge_sigmas=0.0)
    with pytest.raises(ValueError, match="coarse factors"):
        Placement(coarse_factors=(4, 0))


# Fields of RefinementConfig that its digest leaves out, and why.
NOT_DIGESTED = {
    "nodes": "tiling: makes other maplets, whose grids are in their own input hashes",
    "overlap": "tiling and fusion: other maplets, and how they fade into each other",
    "spacing_gsd": "tiling: other maplets",
    "passes": "how often maplets are refined; the catalog's input hash names the pass",
    "max_passes": "how often maplets that have not settled are refined; the input hash names the pass",
    "settled_spacings": "when a maplet is refined again, not how",
    "tile_radius_km": "tiling: which places get maplets",
    "knowledge": "drives the pose adjustment, whose corrections and sigmas are in the input hash",
}


def test_every_setting_is_in_the_digest_or_said_why_not():
    fields = {f.name for f in dataclasses.fields(RefinementConfig)}
    assert set(DEFAULTS.digested()) == fields - set(NOT_DIGESTED)
    assert set(NOT_DIGESTED) <= fields


def _changed(value):
    """A valid value other than `value` (of the same kind)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, tuple):
        return (*value, 1) if all(isinstance(v, int) for v in value) else tuple(v + 1 for v in value)
    return value + 1


@pytest.mark.parametrize("nested", ["placement", "registration", "uncertainty"])
def test_each_placement_registration_and_uncertainty_setting_changes_the_digest(nested):
    settings = getattr(DEFAULTS, nested)
    for f in dataclasses.fields(settings):
        changed = dataclasses.replace(settings, **{f.name: _changed(getattr(settings, f.name))})
        assert dataclasses.replace(DEFAULTS, **{nested: changed}).digest() != DEFAULTS.digest(), f.name
    assert dataclasses.replace(DEFAULTS, knowledge_sigmas=2.0).digest() != DEFAULTS.digest()


def test_the_placement_and_registration_defaults_are_those_refinement_was_tuned_with():
    # the values the module constants of pwm.pipeline and pwm.alignment had, measured in
    # bench/RESULTS.md: a change here is a change of every refinement
    assert DEFAULTS.knowledge_sigmas == 3.0
    assert DEFAULTS.placement == Placement(registration_px=0.1, parallax_rounds=3, runaway=0.8, window_search_px=4,
                                           sweep_start=32.0, sweep_start_many=16.0, sweep_many_images=12,
                                           coarse_factors=(8, 4, 2), resweep_px=8.0)
    assert DEFAULTS.registration == Registration(align_min_nodes=50, align_max_iterations=20, min_coarse_nodes=8)


# -- no tuning constant outside the configuration ----------------------------------------------

# The UPPER_CASE numeric module constants of the modules pwm.pipeline imports, directly or not,
# that stay module constants: none changes what one maplet's refinement gives. Every other one
# belongs in RefinementConfig (or the settings it nests), where its digest names it.
NOT_REFINEMENT = {
    "pwm.fusion.MAX_EDGE_VOXELS": "fusion (the fused surface's faces), after refinement: no maplet's result",
    "pwm.fusion.PLANE_MAX_TILT_DEG": "fusion (when a region is meshed over a plane): no maplet's result",
    "pwm.fusion._COLUMNS": "the layout of the fusion's sums",
    **{f"pwm.fusion.{column}": "a column of the fusion's sums" for column in ("_W", "_WA", "_A")},
    "pwm.knowledge.RADIAL_FRACTION": "the navigation error model of the pose adjustment (its corrections are "
                                     "in the input hash)",
    "pwm.levels.BATCH": "memory: maplets held at a time while fusing",
    "pwm.levels.BLEND_VOXELS": "fusion (how a finer level fades into the one below): no maplet's result",
    "pwm.levels.MAX_EDGE_VOXELS": "fusion (the faces laid onto a level): no maplet's result",
    "pwm.levels.REACH_VOXELS": "fusion (where a finer level's surface is looked for): no maplet's result",
    "pwm.levels.MARGIN_EDGES": "fusion (a laid region's margin): no maplet's result",
    "pwm.levels.SEAL_OVER_EDGES": "import and fusion (how a patch over a hole is sealed into the body): no maplet's "
                                  "result",
    "pwm.photoclinometry._RISE": "numerical: the height step a node's parallax is differenced over; the "
                                 "projection is all but linear over it",
    "pwm.photometry.MCEWEN_L_COEFFS": "physical: McEwen's published lunar-Lambert phase law",
    "pwm.raytrace.CHUNK": "memory: rays traced at a time",
    "pwm.tiling.COVERAGE_SAMPLES_PER_SIDE": "tiling: which maplets are made (each one's grid is in its input hash)",
    "pwm.tiling.COVERAGE_MARGIN": "tiling: which maplets are made (each one's grid is in its input hash)",
    "pwm.tiling._NEAR": "geometry: the ball about a maplet's origin that holds the box searched",
    "pwm.trajectory.ARC_GAP_S": "the navigation arcs of the pose adjustment (its corrections are in the input hash)",
    "pwm.trajectory.SPIN_AXIS": "physical: the body's pole in its body-fixed frame",
    "pwm.trajectory.BASIS_TERMS": "the navigation error model's terms (pose adjustment)",
    "pwm.trajectory.MIN_SPAN_KM": "the navigation frames of the pose adjustment",
    "pwm.views.CONE_MARGIN_RAD": "a pre-selection of the images that may see a place; each is then traced",
    "pwm.views._PAIRS_AT_ONCE": "memory: cone pairs tested at a time",
    "pwm.volume.TRUNCATION_VOXELS": "fusion (signed distances): no maplet's result",
    "pwm.volume.BASE_WEIGHT": "fusion (the base's weight against the maplets'): no maplet's result",
    "pwm.volume.FADE_VOXELS": "fusion (the base's bend towards the maplets): no maplet's result",
    "pwm.volume.BLOCK": "memory: marching cubes' blocks",
    "pwm.volume.MAX_SURFACE_CELLS": "memory and fusion: a closed surface or regions, after refinement",
    "pwm.volume._BEND_NEIGHBOURS": "fusion (the base's bend): no maplet's result",
    "pwm.volume._RING_BATCH": "memory: the points the fusion's rings take at a time (the same rings)",
    "pwm.volume._COLUMNS": "the layout of the fusion's sums",
    **{f"pwm.volume.{column}": "a column of the fusion's sums" for column in ("_W", "_WD", "_WA", "_A")},
    "pwm.voxels._KEY_BITS": "how voxel keys are packed",
    "pwm.voxels._KEY_OFFSET": "how voxel keys are packed",
    "pwm.voxels._KEY_MASK": "how voxel keys are packed",
    "pwm.voxels._BATCH": "memory: maplets added at a time",
}

_CONSTANT = re.compile(r"_?[A-Z][A-Z0-9_]*")


def _spec(name: str):
    try:
        return importlib.util.find_spec(name)
    except ModuleNotFoundError:  # a name inside a module, not a module
        return None


def _imported_pwm_modules(root: str) -> set[str]:
    """`root` and every pwm module it imports, directly or through others, at the top or inside
    functions (read with ast)."""
    found: set[str] = set()
    todo = [root]
    while todo:
        name = todo.pop()
        spec = None if name in found or name.split(".")[0] != "pwm" else _spec(name)
        if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
            continue
        found.add(name)
        package = name if spec.submodule_search_locations is not None else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(Path(spec.origin).read_text())):
            if isinstance(node, ast.Import):
                todo += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                module = importlib.util.resolve_name("." * node.level + (node.module or ""), package)
                todo += [module] + [f"{module}.{a.name}" for a in node.names]  # a name may be a submodule
    return found


def _numeric(value) -> bool:
    if isinstance(value, tuple):
        return len(value) > 0 and all(_numeric(v) for v in value)
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _module_constants(names: set[str]) -> dict[str, object]:
    """The UPPER_CASE numeric constants assigned at the top of each module (module.NAME: value)."""
    out = {}
    for name in sorted(names):
        spec = importlib.util.find_spec(name)
        assert spec is not None and spec.origin is not None
        module = importlib.import_module(name)
        for node in ast.parse(Path(spec.origin).read_text()).body:
            targets = (node.targets if isinstance(node, ast.Assign)
                       else [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else [])
            for target in targets:
                for leaf in ast.walk(target):
                    if isinstance(leaf, ast.Name) and _CONSTANT.fullmatch(leaf.id):
                        value = getattr(module, leaf.id)
                        if _numeric(value):
                            out[f"{name}.{leaf.id}"] = value
    return out


def test_refinement_is_reached_through_these_modules():
    modules = _imported_pwm_modules("pwm.pipeline")
    assert {"pwm.pipeline", "pwm.alignment", "pwm.photoclinometry", "pwm.weights", "pwm.tiling", "pwm.levels",
            "pwm.config"} <= modules


def test_no_constant_that_changes_a_refinement_lives_outside_its_configuration():
    constants = _module_constants(_imported_pwm_modules("pwm.pipeline"))
    unexplained = sorted(set(constants) - set(NOT_REFINEMENT))
    assert not unexplained, (f"module constants {unexplained}: put each that changes a refinement into "
                             "pwm.config.RefinementConfig (or the settings it nests), or list it in "
                             "NOT_REFINEMENT with why it changes none")
    assert not set(NOT_REFINEMENT) - set(constants), "NOT_REFINEMENT names constants that are gone"


def test_a_new_tuning_constant_in_the_pipeline_would_be_found(tmp_path, monkeypatch):
    spec = importlib.util.find_spec("pwm.pipeline")
    assert spec is not None and spec.origin is not None
    source = Path(spec.origin).read_text()
    package = tmp_path / "pwm_probe"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "pipeline.py").write_text(source + "\nSWEEP_AGAIN_PX = 4.0\n_QUIET_STEPS = (1, 2)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    found = _module_constants({"pwm_probe.pipeline"})
    assert set(found) == {"pwm_probe.pipeline.SWEEP_AGAIN_PX", "pwm_probe.pipeline._QUIET_STEPS"}


def test_passes_go_on_where_a_maplet_has_not_settled():
    config = dataclasses.replace(DEFAULTS, passes=2, max_passes=4, settled_spacings=0.3)
    assert config.most_passes == 4
    # every maplet gets its passes, whatever it did
    assert config.another_pass(done=1, changed_spacings=None)
    assert config.another_pass(done=1, changed_spacings=0.0)
    # then another while its last pass still changed it, up to the most passes
    assert config.another_pass(done=2, changed_spacings=0.31)
    assert not config.another_pass(done=2, changed_spacings=0.29)
    assert not config.another_pass(done=2, changed_spacings=None)  # not known: as settled
    assert config.another_pass(done=3, changed_spacings=5.0)
    assert not config.another_pass(done=4, changed_spacings=5.0)
    # never fewer than the passes every maplet gets; one pass has nothing to compare with
    assert dataclasses.replace(config, passes=5).most_passes == 5
    assert dataclasses.replace(config, passes=1).most_passes == 1
    with pytest.raises(ValueError, match="settled"):
        dataclasses.replace(config, settled_spacings=0.0)
