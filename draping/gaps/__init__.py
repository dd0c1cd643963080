"""GAPS: geometry-aware, physics-based, self-supervised neural garment draping (thesis ch. 4).

A garment-specific GRU regressor (:class:`GapsModel`) maps body shape, pose and root velocity
to displacements of the unposed garment, which is then skinned with RBF body-participation
weights (eq. (37)); it is trained without data by the cloth energies of
:mod:`draping.physics` (eq. (38)-(46)) on procedural motions and random Anny shapes. The
SNUG-like and NCS-like baselines and the paper's ablations are settings of the same code.

``settings`` (:class:`GapsSettings`, :class:`TrainSettings`), ``model`` (the network and its
inputs), ``data`` (garment per shape, motions, held-out cases), ``losses`` (eq. (38)-(46) from
:mod:`draping.physics`), ``train`` (:func:`train`), ``infer`` (:func:`load_model`,
:func:`drape_sequence`, :func:`evaluate`), ``cli`` (``polygeo train-drape``, ``polygeo drape``).

Example (the API a benchmark uses)::

    from draping.gaps import TrainSettings, GapsSettings, train, load_model, evaluate
    run = train(TrainSettings(GapsSettings(garment="dress", method="snug")), "runs/snug",
                minutes=30)
    print(evaluate(load_model(run.model_path))["mean"])     # held-out eps_e, eps_a, eps_c (%)
"""

from typing import TYPE_CHECKING

from polygeo.lazy import attach

if TYPE_CHECKING:
    from .average import WeightAverage
    from .data import (
        VALIDATION_RANDOM_SEEDS,
        Case,
        Sequence,
        ShapeCase,
        check_case,
        check_phenotypes,
        garment_weights,
        held_out_cases,
        random_cases,
        random_shapes,
        sequence_of,
        shape_case,
        stress_cases,
        template_garment,
        training_sequences,
        validation_cases,
        validation_random_cases,
    )
    from .infer import (
        Drape,
        build_model,
        check_garment_for,
        drape_case,
        drape_motion,
        drape_sequence,
        evaluate,
        frame_metrics,
        garment_key,
        load_model,
        model_garment,
        motion_features,
        save_model,
        shipped_garments,
        shipped_model_path,
        time_inference,
    )
    from .losses import TERMS, body_contacts, loss_terms
    from .model import GapsModel, feature_size, pose_features, top_weights
    from .pinch import PARTS, PinchQuery, body_part, face_parts, pinch_factor, push_normal
    from .settings import (
        HELD_OUT_MOTIONS,
        INEXTENSIBILITY,
        METHODS,
        POSE_BONES,
        TRAIN_MOTIONS,
        GapsSettings,
        TrainSettings,
    )
    from .train import STAGES, Trainer, TrainResult, train, untrained_model

__getattr__, __dir__ = attach(__name__, __file__)

__all__ = [
    "WeightAverage",
    "Case",
    "Sequence",
    "ShapeCase",
    "check_case",
    "check_phenotypes",
    "garment_weights",
    "held_out_cases",
    "validation_cases",
    "random_cases",
    "validation_random_cases",
    "VALIDATION_RANDOM_SEEDS",
    "random_shapes",
    "sequence_of",
    "shape_case",
    "stress_cases",
    "template_garment",
    "training_sequences",
    "Drape",
    "build_model",
    "check_garment_for",
    "drape_case",
    "drape_motion",
    "drape_sequence",
    "evaluate",
    "frame_metrics",
    "garment_key",
    "load_model",
    "model_garment",
    "motion_features",
    "save_model",
    "shipped_model_path",
    "shipped_garments",
    "time_inference",
    "TERMS",
    "body_contacts",
    "loss_terms",
    "GapsModel",
    "feature_size",
    "pose_features",
    "top_weights",
    "PARTS",
    "PinchQuery",
    "body_part",
    "face_parts",
    "pinch_factor",
    "push_normal",
    "HELD_OUT_MOTIONS",
    "INEXTENSIBILITY",
    "METHODS",
    "POSE_BONES",
    "TRAIN_MOTIONS",
    "GapsSettings",
    "TrainSettings",
    "STAGES",
    "Trainer",
    "TrainResult",
    "train",
    "untrained_model",
]
