"""The stage contract as code: kintinuous_fast's modules have kintinuous_ref's public names and
signatures (docs/architecture.md).

For every stage, and for every estimator of the odometry, the reference module is compared with
the fast cpu and cuda modules. A name counts as public in the reference when it is a function or
class defined in that module whose name does not start with "_"; in a fast module, when it is in
the module's `__all__` (which every fast module declares). Both sets must be equal, and every
name in both must have the same signature: the same parameters, in the same order, of the same
kind, with the same defaults (annotations may differ: a cuda function takes device arrays where
the reference takes NumPy arrays). A class that is the reference's own object is the same by
definition. Any deliberate difference is listed in DELIBERATE below, with its reason; nowhere else.
"""

from __future__ import annotations

import importlib
import inspect
import types
from typing import Any

import pytest

TARGETS = ("cpu", "cuda")

# Reference module -> the fast modules (one per target) that mirror it.
MIRRORS: dict[str, tuple[str, ...]] = {
    "kintinuous_ref.preprocess": tuple(f"kintinuous_fast.preprocess.{t}" for t in TARGETS),
    "kintinuous_ref.tsdf": tuple(f"kintinuous_fast.tsdf.{t}" for t in TARGETS),
    "kintinuous_ref.raycast": tuple(f"kintinuous_fast.raycast.{t}" for t in TARGETS),
    "kintinuous_ref.colour": tuple(f"kintinuous_fast.colour.{t}" for t in TARGETS),
    # The odometry: the trackers (the stage module), then one estimator each.
    "kintinuous_ref.odometry": tuple(f"kintinuous_fast.odometry.{t}" for t in TARGETS),
    "kintinuous_ref.odometry.icp": tuple(f"kintinuous_fast.odometry.icp.{t}" for t in TARGETS),
    "kintinuous_ref.odometry.rgbd": tuple(f"kintinuous_fast.odometry.rgbd.{t}" for t in TARGETS),
    "kintinuous_ref.odometry.solve": tuple(
        f"kintinuous_fast.odometry.solve.{t}" for t in TARGETS
    ),
    "kintinuous_ref.marching_cubes": tuple(f"kintinuous_fast.mesh.{t}" for t in TARGETS),
    # Host code compiled once for both targets.
    "kintinuous_ref.odometry.combined": ("kintinuous_fast.odometry.combined",),
}

# (fast module, name) -> why it differs from the reference. The one place for exceptions.
_FAST_VOLUME = (
    "the fast volume type (int16 TSDF and weight, packed colour: 8 bytes a voxel; in device "
    "memory for cuda), which make_volume returns and every fast function takes"
)
_REFERENCE_VIEW = (
    "the fast volume as the reference's TsdfVolume on the host, for meshing and output "
    "(Backend.host_volume)"
)
_NO_HOST_COLOUR = (
    "the fast raycast reads the colour volume inside its kernel (tsdf/voxel.py); host code "
    "reads colours from Backend.host_volume, the reference's TsdfVolume"
)
DELIBERATE: dict[tuple[str, str], str] = {
    **{(f"kintinuous_fast.tsdf.{t}", "FastTsdfVolume"): _FAST_VOLUME for t in TARGETS},
    **{(f"kintinuous_fast.tsdf.{t}", "TsdfVolume"): _FAST_VOLUME for t in TARGETS},
    **{(f"kintinuous_fast.tsdf.{t}", "to_reference_volume"): _REFERENCE_VIEW for t in TARGETS},
    **{(f"kintinuous_fast.colour.{t}", "surface_colour"): _NO_HOST_COLOUR for t in TARGETS},
}


def reference_names(module: types.ModuleType) -> set[str]:
    """The functions and classes `module` defines itself, but for those starting with "_"."""
    return {
        name
        for name, value in vars(module).items()
        if not name.startswith("_")
        and (inspect.isfunction(value) or inspect.isclass(value))
        and getattr(value, "__module__", None) == module.__name__
    }


def parameters(value: Any) -> list[tuple[str, Any, Any]]:
    """(name, kind, default) of each parameter of a function or a class's constructor; numba's
    compiled functions by their Python function."""
    signature = inspect.signature(getattr(value, "py_func", value))
    return [(p.name, p.kind, p.default) for p in signature.parameters.values()]


def same_parameters(a: Any, b: Any) -> bool:
    if a is b:
        return True
    left, right = parameters(a), parameters(b)
    if len(left) != len(right):
        return False
    for (name_a, kind_a, default_a), (name_b, kind_b, default_b) in zip(left, right, strict=True):
        if (name_a, kind_a) != (name_b, kind_b):
            return False
        if default_a is not default_b and not bool(default_a == default_b):
            return False
    return True


def describe(value: Any) -> str:
    return str(inspect.signature(getattr(value, "py_func", value)))


def contract_problems(
    reference: types.ModuleType,
    fast: types.ModuleType,
    deliberate: dict[tuple[str, str], str],
) -> list[str]:
    """One line per breach of the contract between `reference` and `fast` that `deliberate`
    does not excuse (a missing `__all__` is never excused)."""
    exported = getattr(fast, "__all__", None)
    if exported is None:
        return [f"{fast.__name__} declares no __all__"]
    problems = []
    ours, theirs = reference_names(reference), set(exported)
    for name in sorted(ours | theirs):
        if (fast.__name__, name) in deliberate:
            continue
        if name not in theirs:
            problems.append(f"{fast.__name__} lacks {reference.__name__}.{name}")
        elif not hasattr(fast, name):
            problems.append(f"{fast.__name__}.__all__ names {name}, which it does not define")
        elif name not in ours:
            # A name the reference only imports or assigns (a constant, a shared type) counts
            # when the fast module exports that very object.
            if getattr(reference, name, None) is not getattr(fast, name):
                problems.append(f"{fast.__name__}.{name} has no namesake in {reference.__name__}")
        else:
            mine, yours = getattr(reference, name), getattr(fast, name)
            if callable(mine) and not same_parameters(mine, yours):
                problems.append(
                    f"{fast.__name__}.{name}{describe(yours)} differs from "
                    f"{reference.__name__}.{name}{describe(mine)}"
                )
    return problems


PAIRS = [(ref, fast) for ref, fasts in MIRRORS.items() for fast in fasts]


@pytest.mark.parametrize(("reference", "fast"), PAIRS, ids=[fast for _, fast in PAIRS])
def test_fast_module_keeps_the_reference_contract(reference, fast):
    problems = contract_problems(
        importlib.import_module(reference), importlib.import_module(fast), DELIBERATE
    )
    assert problems == []


def test_every_deliberate_difference_is_still_a_difference():
    """An exception that no longer excuses anything is removed, so the list stays true."""
    for fast_name, name in DELIBERATE:
        reference = next(ref for ref, fasts in MIRRORS.items() if fast_name in fasts)
        problems = contract_problems(
            importlib.import_module(reference), importlib.import_module(fast_name), {}
        )
        assert any(f".{name}" in problem or f" {name}" in problem for problem in problems), (
            fast_name,
            name,
        )


# The contract test's own test: it fails when a name or a signature drifts.


def _module(name: str, **values: Any) -> types.ModuleType:
    module = types.ModuleType(name)
    for key, value in values.items():
        if inspect.isfunction(value):
            value.__module__ = name
        setattr(module, key, value)
    return module


def _reference() -> types.ModuleType:
    def integrate(volume, depth, pose, camera, colour=None):  # noqa: ARG001
        return None

    def check_depth(depth, camera):  # noqa: ARG001
        return None

    return _module("ref_stage", integrate=integrate, check_depth=check_depth)


def test_the_contract_holds_for_equal_modules():
    reference = _reference()
    fast = _module("fast_stage", **{n: getattr(reference, n) for n in ("integrate", "check_depth")})
    fast.__all__ = ["integrate", "check_depth"]
    assert contract_problems(reference, fast, {}) == []


def test_the_contract_fails_on_a_drifted_signature():
    reference = _reference()

    def integrate(volume, depth, pose, camera, colour=None, download=True):  # noqa: ARG001
        return None

    fast = _module("fast_stage", integrate=integrate, check_depth=reference.check_depth)
    fast.__all__ = ["integrate", "check_depth"]
    (problem,) = contract_problems(reference, fast, {})
    assert problem.startswith("fast_stage.integrate(") and "download=True" in problem


def test_the_contract_fails_on_a_changed_default_a_missing_and_an_extra_name():
    reference = _reference()

    def integrate(volume, depth, pose, camera, colour=0):  # noqa: ARG001
        return None

    def negative_masks(volume):  # noqa: ARG001
        return None

    fast = _module("fast_stage", integrate=integrate, negative_masks=negative_masks)
    fast.__all__ = ["integrate", "negative_masks"]
    problems = contract_problems(reference, fast, {})
    assert problems == [
        "fast_stage lacks ref_stage.check_depth",
        "fast_stage.integrate(volume, depth, pose, camera, colour=0) differs from "
        "ref_stage.integrate(volume, depth, pose, camera, colour=None)",
        "fast_stage.negative_masks has no namesake in ref_stage",
    ]
    excused = {("fast_stage", "check_depth"): "r", ("fast_stage", "negative_masks"): "r"}
    assert len(contract_problems(reference, fast, excused)) == 1


def test_the_contract_fails_on_a_real_module_that_drifts(monkeypatch):
    """The same check on a real fast module, its function replaced by one with another
    parameter name."""
    from kintinuous_fast.colour import cpu
    from kintinuous_ref import colour

    def colour_weights(frame, settings):  # noqa: ARG001
        return None

    monkeypatch.setattr(cpu, "colour_weights", colour_weights)
    problems = contract_problems(colour, cpu, DELIBERATE)
    assert any(p.startswith("kintinuous_fast.colour.cpu.colour_weights(") for p in problems)


def test_a_fast_module_without_all_breaks_the_contract():
    assert contract_problems(_reference(), _module("fast_stage"), {}) == [
        "fast_stage declares no __all__"
    ]
