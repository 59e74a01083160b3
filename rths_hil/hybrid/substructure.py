"""The numerical side of a plan (:mod:`rths_hil.hybrid.plan`): the ground motion, a channel's
twin plant, the MDOF model and the structure stage of ``structure.kind``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import groundmotion
from ..config import Config, check_table, structure_dofs
from ..errors import InputError
from ..keys import Key
from ..structures.sdof import BoucWenParams, CRStepper
from ..structures.stages import MDOFStage, SDOFStage, StructureStage

__all__ = [
    "build_ground_motion",
    "build_model",
    "build_structure",
    "choose_plant",
    "structure_size",
]

#: The keys of ``structure.matrices`` (:func:`build_model`): one ``.npz`` file, or CSV files.
_MATRICES_KEYS: dict[str, Key] = {
    "file": Key("str", None, doc="an .npz file holding the arrays M, K and C (or zeta)"),
    "M": Key("str", None, doc="CSV file of the mass matrix"),
    "K": Key("str", None, doc="CSV file of the stiffness matrix"),
    "C": Key("str", None, doc="CSV file of the damping matrix"),
}


def build_ground_motion(cfg: Config) -> groundmotion.GroundMotion:
    """The configured record: loaded, PGA-scaled, padded with the tail, resampled to ``fs``."""
    g = cfg["ground_motion"]
    spec = g["record"]
    try:
        if spec == "default":
            gm = groundmotion.default_record()
        else:
            p = cfg.resolve_path(spec)
            gm = groundmotion.load(p) if p.is_file() else groundmotion.resolve(spec)
        if g["pga"] > 0:
            gm = gm.scaled(g["pga"])
        if g["tail"] > 0:
            gm = gm.padded(g["tail"])
        return gm.resampled(cfg["loop"]["fs"])
    except InputError as exc:
        raise InputError(
            f"{cfg.where('ground_motion.record')}: ground_motion.record: {exc}"
        ) from None
    except OSError as exc:  # a path component over 255 characters, a directory, no permission
        raise InputError(
            f"{cfg.where('ground_motion.record')}: ground_motion.record: cannot read {spec!r}: "
            f"{exc.strerror or exc}"
        ) from None


def choose_plant(cfg: Config, dt: float):
    """The twin's plant of a channel (``cfg`` is the channel's resolved configuration).

    ``twin.model`` (a model file) or the ``twin.actuator`` / ``specimen`` / ``sensor`` tables,
    built by :func:`rths_hil.sim_backends.modelfile.build_plant`; a force or load channel
    (``control.mode``) gets the force-controlled twin of the same tables
    (:func:`rths_hil.sim_backends.force.force_plant`, force-loop gain ``twin.force_loop_gain``).
    This is the one place the loop chooses a twin.
    """
    from rths_hil.sim_backends.modelfile import build_plant

    tw = cfg["twin"]
    try:
        if cfg["control"]["mode"] != "displacement":  # a force or load channel: the force twin
            from rths_hil.sim_backends.force import force_plant

            source = cfg.resolve_path(tw["model"]) if tw["model"] else tw
            return force_plant(source, dt, tw["force_loop_gain"])
        return build_plant(tw, dt, str(cfg.base_dir))
    except InputError as exc:
        where = "twin.model: " if tw["model"] else "twin."  # the message names the table key
        raise InputError(f"{cfg.source}: {where}{exc}") from None


def build_model(cfg: Config):
    """The MDOF model of ``structure.kind`` (``shear_building`` or ``matrices``), no integrator.

    Damping: ``structure.rayleigh = [α, β]`` when given, else ζ = ``structure.damping`` on
    modes 1 and 2 (Rayleigh), or the file's ``C``. Bouc-Wen storeys (``bouc_wen = true``) take
    the shape keys of ``[structure]`` with each storey's stiffness as ``k_a``.
    """
    from ..structures import mdof

    s = cfg["structure"]
    damping: dict[str, Any] = (
        {"rayleigh": tuple(s["rayleigh"])} if s["rayleigh"] else {"zeta": s["damping"]}
    )
    if s["kind"] == "shear_building":
        bw = None
        if s["bouc_wen"]:
            bw = {k: s[k] for k in ("x_y", "eta", "beta", "gamma", "q")}
        return mdof.shear_building(s["masses"], s["stiffnesses"], bouc_wen=bw, **damping)
    files = check_table(s["matrices"], _MATRICES_KEYS, path="matrices", defaults=False)
    if "file" in files:
        return mdof.load_npz(cfg.resolve_path(str(files["file"])), **damping)
    if "M" not in files or "K" not in files:
        raise InputError("matrices: give {file = 'model.npz'} or the CSV files M and K (and C)")
    paths = {k: cfg.resolve_path(str(v)) for k, v in files.items()}
    if "C" in paths:
        return mdof.load_csv(paths["M"], paths["K"], paths["C"])
    return mdof.load_csv(paths["M"], paths["K"], **damping)


def _site_dofs(cfg: Config) -> int:
    """Number of DOFs of an OpenFresco site: its actuators (:func:`structure_dofs`)."""
    dofs = structure_dofs(cfg)
    assert dofs is not None  # known for kind "openfresco"
    return dofs


def structure_size(cfg: Config) -> tuple[int, Any]:
    """Number of DOFs and the MDOF model (None for the SDOF frame)."""
    if cfg["structure"]["kind"] == "sdof":
        return 1, None
    if cfg["structure"]["kind"] == "openfresco":
        return _site_dofs(cfg), None
    try:
        model = build_model(cfg)
    except InputError as exc:
        raise InputError(f"{cfg.source}: structure: {exc}") from None
    return model.n, model


def build_structure(
    cfg: Config, dt: float, ag0: float, rows: np.ndarray, model: Any = None
) -> tuple[StructureStage, float]:
    """The structure stage of ``structure.kind`` and its first natural frequency (Hz).

    ``sdof``: the FEI paper's Section 5 frame (CR integration, Bouc-Wen). ``shear_building`` and
    ``matrices``: the CR integrator in matrix form of :mod:`rths_hil.structures.mdof`, with
    ``structure.k_specimen`` seen through each actuator's transform row in α (``rows``).
    """
    s = cfg["structure"]
    if s["kind"] == "openfresco":  # OpenSees computes the targets (rths_hil.openfresco)
        from ..openfresco.stage import SiteStage

        try:
            return SiteStage(cfg["openfresco"], dt, _site_dofs(cfg)), float(s["fn"])
        except InputError as exc:
            raise InputError(f"{cfg.source}: {exc}") from None
    if s["kind"] == "sdof":
        k_struct = s["mass"] * (2.0 * math.pi * s["fn"]) ** 2
        bw = None
        if s["bouc_wen"]:
            bw = BoucWenParams(
                x_y=s["x_y"], k_a=k_struct, eta=s["eta"], beta=s["beta"], gamma=s["gamma"], q=s["q"]
            )
        try:
            st = CRStepper(
                s["mass"],
                s["damping"],
                k_struct,
                dt,
                bouc_wen=bw,
                k_specimen=s["k_specimen"],
                ag0=ag0,
            )
        except InputError as exc:
            raise InputError(f"{cfg.source}: structure: {exc}") from None
        return SDOFStage(st), float(s["fn"])
    from ..structures.mdof import MDOFCRStepper

    if model is None:
        model = structure_size(cfg)[1]
    try:
        stepper = MDOFCRStepper(
            model, dt, transforms=rows, k_specimen=[s["k_specimen"]] * len(rows), ag0=ag0
        )
    except InputError as exc:
        raise InputError(f"{cfg.source}: structure: {exc}") from None
    return MDOFStage(stepper), float(model.frequencies[0])
