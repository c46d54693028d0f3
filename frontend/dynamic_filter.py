"""Building the dynamic filter a config asks for: the enabled methods, the detector they need (unless
one is given, e.g. ground-truth boxes of a generated sequence) and their fusion, or the null filter.

Kept apart from ``frontend.dynamic`` because the detector module imports that package (its
``Detection`` type): the factory sits above both, so neither imports the other back.

Without a detector model (none given explicitly, none in the cache or the development folder) a config
that asks for detector methods still runs when it also has a method that needs none (cpr): that one
goes on alone, with one warning saying what was dropped and the command that fetches the model. With
only detector methods left nothing would run, so that is an error giving the command. A model path
given explicitly that does not exist stays an error (exit status 2): the user asked for that file.
"""
from __future__ import annotations

import importlib
import warnings
from typing import Optional

from frontend.detector import build_detector
from frontend.dynamic import DynamicFilter, StaticWorld
from frontend.dynamic.base import Detector
from frontend.dynamic.rejector import DynamicRejector
from frontend.model_lookup import ModelNotFoundError, download_command, locate_model, missing_model_message
from slam.core.camera import PinholeCamera
from slam.core.timing import ModuleTimer

# method name -> (module, class, config attribute, takes class groups)
_METHODS = {
    "cpr": ("frontend.dynamic.cpr", "CprMethod", "cpr", False),
    "box_depth": ("frontend.dynamic.box_depth", "BoxDepthMethod", "box_depth", True),
    "flow_epipolar": ("frontend.dynamic.flow_epipolar", "FlowEpipolarMethod", "flow_epipolar", True),
    "depth_sdf": ("frontend.dynamic.depth_sdf", "DepthSdfMethod", "depth_sdf", True),
}


def build_method(name: str, config):
    module_name, class_name, cfg_attr, takes_classes = _METHODS[name]
    cls = getattr(importlib.import_module(module_name), class_name)
    method_cfg = getattr(config.dynamic, cfg_attr)
    return cls(method_cfg, config.dynamic.classes) if takes_classes else cls(method_cfg)


class DetectorModelMissingWarning(RuntimeWarning):
    """Detector methods were dropped from a run because no detector model was found."""


def build_dynamic_filter(config, camera: PinholeCamera, timer: Optional[ModuleTimer] = None,
                         sequence_name: str = "", detector: Optional[Detector] = None) -> DynamicFilter:
    """The filter for ``config.dynamic``: the null filter, or the enabled methods and their fusion.

    When methods (or the box prior) need a detector, none is given, and no model file is found
    implicitly, the detector-free methods run alone (see ``without_detector``)."""
    dynamic = config.dynamic
    if not dynamic.methods and dynamic.box_prior <= 0:
        return StaticWorld()
    methods = [build_method(name, config) for name in dynamic.methods]
    if detector is None and (any(m.needs_detector for m in methods) or dynamic.box_prior > 0):
        location = locate_model(dynamic.detector)
        if location.path is None and not location.explicit:
            methods, dynamic = without_detector(methods, dynamic, location.searched)
        else:
            detector = build_detector(dynamic.detector, dynamic.classes, sequence_name)
    return DynamicRejector(dynamic, camera, methods, detector, timer)


def without_detector(methods: list, dynamic, searched=()) -> tuple[list, object]:
    """The methods that need no detector and the dynamic config they run under, after ONE warning;
    ModelNotFoundError (with the download command) when no method would be left, since a run that
    asked only for detector methods would otherwise quietly be a run without dynamic handling.

    The box prior is switched off with the detector methods. A single remaining method runs with
    fusion 'single', as its own preset does (configs/dynamic_cpr.yaml): under noisy-OR its weight in a
    fused preset (cpr: 0.2 in dynamic_all) is chosen to need a second method's agreement, so alone it
    would never flag a feature."""
    kept = [m for m in methods if not m.needs_detector]
    if not kept:
        raise ModelNotFoundError(missing_model_message(dynamic.detector.model, tuple(searched)))
    dropped = [m.name for m in methods if m.needs_detector]
    dropped += ["the person-box prior"] if dynamic.box_prior > 0 else []
    fusion = "single" if len(kept) == 1 else dynamic.fusion
    reduced = dynamic.model_copy(update=dict(methods=[m.name for m in kept], box_prior=0.0, fusion=fusion))
    places = " or ".join(str(p) for p in searched) or "the usual places"
    warnings.warn(f"no detector model '{dynamic.detector.model}' found (looked for {places}); continuing "
                  f"with {', '.join(m.name for m in kept)} only "
                  f"({', '.join(dropped)} need the detector). Get the model with: "
                  f"{download_command(dynamic.detector.model)}", DetectorModelMissingWarning, stacklevel=3)
    return kept, reduced


def method_names(dynamic_filter: DynamicFilter) -> list[str]:
    """The methods a built filter runs (after any fallback above), for run summaries."""
    if isinstance(dynamic_filter, DynamicRejector):
        return [m.name for m in dynamic_filter.methods]
    return [] if isinstance(dynamic_filter, StaticWorld) else [dynamic_filter.name]
