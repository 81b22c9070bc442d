"""Results -> JSON documents: what ``softgrip estimate --json`` and ``softgrip score --json`` write.

Each command writes ONE JSON document (schemas in ``softgrip_base/schemas/estimate.schema.json``
and ``softgrip_base/schemas/score.schema.json``, :func:`schema`) that says what its numbers mean: ``units``,
``conventions`` (origin, axes, units and the plane's depth: :func:`softgrip_vision.scene.conventions`), the
``profile`` it was made with (:func:`profile_identity`), then a list per frame (estimate) or per
candidate pose (score). Every enum is written by name (cases ``"none"``, ``"tip"``, ...; statuses
``"ok"``, ``"base_outside_sdf"``, ...). One finger is written as::

    {"side": "left"|"right", "valid": bool, "status": "ok"|"non_finite_input"|... (Status names),
     "case": "none"|"tip"|"tip_and_other"|"other", "theta_entire": rad,
     "joints_px": [[u, v], ...], "joints_mm": [[x, y], ...],    # N+1 joints, base (0) to tip (N)
     "contacts_px": [[u, v], ...], "contacts_mm": [[x, y], ...],  # P_o1, and P_o2 for tip_and_other
     "event": bool, "sensitivity": mm/mm}  # mechanics: near a jump of the closing path; tip / base motion

A scored candidate's fingers (:func:`candidate_json`) hold the contacts the grasp quality is computed
from instead (up to ``CONTACTS_PER_FINGER`` a finger, base to tip), with two lists parallel to them::

     "contacts_px": [...], "contacts_mm": [...],  # the quality's contacts on the object
     "normals": [[nx, ny], ...],                  # the object's outward unit normals there
     "forces": [[fx, fy], ...] | null,            # force on the object, EI / L^2; null: geometric estimate

and the candidate has ``quality`` (Ferrari-Canny L1 epsilon; null when not valid), ``force_closure``,
``centroid_mm`` and ``rho_mm`` (the object's area centroid, and its largest distance from it: torques
are about the centroid, over rho).

Coordinates that are not finite (an invalid candidate outside the image) are written as null.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from importlib import resources
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

from softgrip_jax import CASE_NAMES, ContactCase, Status, code_names

SIDES: tuple[str, str] = ("left", "right")
#: Version of each kind of document's layout (``"format"`` field); additions keep it, changes bump
#: it. Score 2: a score finger's ``contacts_mm`` are the grasp quality's contacts (with ``normals`` and
#: ``forces``), no longer P_o1 and P_o2.
DOCUMENT_VERSIONS = {"estimate": 1, "score": 2}
#: The estimate document's version (kept for callers of the first releases).
DOCUMENT_VERSION = DOCUMENT_VERSIONS["estimate"]
#: Where the JSON Schemas live: package data of softgrip_base (``softgrip_base/schemas/``), in a
#: checkout and in an installed wheel alike.
SCHEMA_DIR = Path(str(resources.files("softgrip_base") / "schemas"))


def schema(kind: str) -> dict:
    """The JSON Schema of the ``"estimate"`` or ``"score"`` document."""
    return json.loads((SCHEMA_DIR / f"{kind}.schema.json").read_text(encoding="utf-8"))


def points_json(points: np.ndarray, decimals: int) -> list:
    """(K, 2) points as [[a, b], ...], rounded, with null for non-finite coordinates."""
    out = []
    for row in np.asarray(points, np.float64).reshape(-1, 2):
        out.append([round(float(v), decimals) if math.isfinite(v) else None for v in row])
    return out


def number_json(value, decimals: int = 6):
    """A float rounded, or null when not finite."""
    value = float(value)
    return round(value, decimals) if math.isfinite(value) else None


def status_name(status: int, penetrating: bool = False) -> str:
    """A candidate's status (one integer code) as JSON text: ``softgrip_jax.Status`` names in lower
    case (:func:`softgrip_jax.code_names`), ``"status_<code>"`` for a code ``Status`` does not have,
    or ``"penetrating"`` for an estimate that is usable (code 0) but flagged by the score."""
    status = int(status)
    if status == 0 and penetrating:
        return "penetrating"
    return str(code_names(status, Status, unknown="status_{}"))


def finger_contacts_mm(estimate) -> np.ndarray:
    """(P, 2) contact points on the object, mm: none for case (a), P_o1, and P_o2 for case (c)."""
    case = int(estimate.case)
    if case == ContactCase.NONE:
        return np.zeros((0, 2))
    points = [np.asarray(estimate.contact.p_o1, np.float64)]
    if case == ContactCase.TIP_AND_OTHER:
        points.append(np.asarray(estimate.contact.p_o2, np.float64))
    return np.stack(points)


class QualityContacts(TypedDict):
    """One finger's touching contacts (:func:`quality_contacts`): parallel (P, 2) arrays."""

    points: np.ndarray  #: (P, 2) mm on the object
    normals: np.ndarray  #: (P, 2) the object's outward unit normals
    forces: np.ndarray | None  #: (P, 2) EI / L^2 on the object; None for an estimate without forces


def quality_contacts(contacts, index: int) -> QualityContacts:
    """One finger's contacts of a scored candidate: ``contacts`` is the numpy
    :class:`softgrip_jax._quality.FingerContacts` of a ``Score`` (leaves of leading axis 2: left,
    right), ``index`` 0 (left) or 1 (right). Returns the slots that touch, in order, as parallel
    arrays: ``points`` (P, 2) mm on the object, ``normals`` (P, 2) the object's outward unit normals,
    ``forces`` (P, 2) the contact forces on the object in EI / L^2 (the finger's mean bending
    stiffness over its length squared), or None when the estimate gives no forces (the geometric
    one: every slot NaN)."""
    touching = np.asarray(contacts.touching[index], bool)
    forces = np.asarray(contacts.forces[index], np.float64)
    return {"points": np.asarray(contacts.points[index], np.float64)[touching],
            "normals": np.asarray(contacts.normals[index], np.float64)[touching],
            "forces": None if np.isnan(forces).all() else forces[touching]}


def finger_json(side: str, estimate, finger, camera, contacts: QualityContacts | None = None) -> dict:
    """One finger's fields (see the module docstring) from a numpy ``Estimate``; with ``contacts``
    (:func:`quality_contacts`), a scored candidate's: those contacts, their normals and forces."""
    joints_mm = np.asarray(estimate.joints, np.float64)
    contacts_mm = finger_contacts_mm(estimate) if contacts is None else contacts["points"]
    fields = {
        "side": side,
        "valid": bool(estimate.valid),
        "status": status_name(estimate.status),
        "case": CASE_NAMES[int(estimate.case)],
        "theta_entire": round(float(finger.theta_entire), 6),
        "joints_px": points_json(camera.mm_to_px(joints_mm), 3),
        "joints_mm": points_json(joints_mm, 4),
        "contacts_px": points_json(camera.mm_to_px(contacts_mm), 3),
        "contacts_mm": points_json(contacts_mm, 4),
    }
    if contacts is not None:
        fields["normals"] = points_json(contacts["normals"], 6)
        fields["forces"] = None if contacts["forces"] is None else points_json(contacts["forces"], 6)
    fields["event"] = bool(estimate.event)
    fields["sensitivity"] = number_json(estimate.sensitivity, 3)
    return fields


def fingers_json(grasp, gripper, camera, contacts=None) -> list[dict]:
    """[left, right] finger fields of a numpy ``GraspEstimate``; with ``contacts`` (a numpy
    ``FingerContacts`` of leading axis 2, a ``Score``'s), those of a scored candidate."""
    return [finger_json(side, getattr(grasp, side), getattr(gripper, side), camera,
                        None if contacts is None else quality_contacts(contacts, k)) for k, side in enumerate(SIDES)]


def pose_json(pose: np.ndarray) -> dict:
    """``{"x_mm", "y_mm", "angle_rad"}`` of a (3,) pose."""
    return {"x_mm": round(float(pose[0]), 4), "y_mm": round(float(pose[1]), 4),
            "angle_rad": round(float(pose[2]), 6)}


def frame_json(scene, grasp, method: str) -> dict:
    """``{"frame", "valid", "status", "method", "n_links", "fingers", "pose", "plane"}``: one frame of
    ``softgrip estimate --json`` (``method``: the deformation estimate used). The frame is valid when
    both fingers are; its status is the first invalid finger's (``"ok"`` when both are valid)."""
    fingers = fingers_json(grasp, scene.gripper, scene.camera)
    bad = [f for f in fingers if not f["valid"]]
    return {"frame": scene.path, "valid": not bad, "status": bad[0]["status"] if bad else "ok", "method": method,
            "n_links": scene.n_links, "fingers": fingers, "pose": pose_json(scene.pose),
            "plane": scene.conventions["plane"]}


def failed_frame_json(path: str, method: str, error: str) -> dict:
    """The entry of a frame that could not be estimated at all."""
    return {"frame": path, "valid": False, "status": "error", "error": error, "method": method, "n_links": None,
            "fingers": []}


def components_json(components) -> dict:
    """Score components (a numpy ``ScoreComponents``) as {name: number or [left, right]}."""
    out = {}
    for field in dataclasses.fields(components):
        value = np.asarray(getattr(components, field.name), np.float64)
        out[field.name] = number_json(value) if value.ndim == 0 else [number_json(v) for v in value.ravel()]
    return out


def candidate_json(pose: np.ndarray, scored, gripper, camera, robust: bool = False) -> dict:
    """One scored candidate (a numpy ``Score`` of one pose) as ``softgrip score`` writes it: the
    score, ``quality`` (the Ferrari-Canny L1 epsilon: 0 without force closure, null when not valid),
    ``force_closure``, the object's ``centroid_mm`` and ``rho_mm``, and each finger with the
    quality's contacts (:func:`finger_json`). ``robust``: also ``quality_mean`` and ``p_closure``
    (robust scoring's expected quality and probability of force closure; null when not valid)."""
    valid = bool(scored.valid)
    closure = valid and bool(scored.force_closure)
    robust_fields = {"quality_mean": number_json(scored.quality_mean) if valid else None,
                     "p_closure": number_json(scored.p_closure) if valid else None} if robust else {}
    return {
        "pose": pose_json(pose),
        "score": number_json(scored.score) if valid else None,
        "quality": (number_json(scored.quality) if closure else 0.0) if valid else None,
        "force_closure": closure,
        "centroid_mm": [number_json(v, 4) for v in np.asarray(scored.centroid).ravel()],
        "rho_mm": number_json(scored.rho, 4),
        **robust_fields,
        "components": components_json(scored.components),
        "valid": valid,
        "status": status_name(scored.status, bool(scored.penetrating)),
        "fingers": fingers_json(scored.grasp, gripper, camera, scored.contacts),
    }


def uncertainty_json(uncertainty) -> dict:
    """The document-level ``"robust"`` of ``softgrip score --robust``: the method (``"draws"`` or
    ``"linear"``), the draws (``samples`` and ``seed``, null when linearised) and every standard
    deviation (mm, rad) the uncertainty was given with."""
    names = ("pose_mm", "pose_rad", "mu_spread", "theta", "length", "stiffness_ratio", "base_compliance", "contour_mm")
    linear = bool(uncertainty.linear)
    return {"method": "linear" if linear else "draws",
            "samples": None if linear else int(uncertainty.samples), "seed": None if linear else int(uncertainty.seed),
            **{name: number_json(getattr(uncertainty, name), 6) for name in names}}


def friction_json(mu: float) -> dict:
    """The document-level ``"friction"`` of ``softgrip score``: ``{"mu": Coulomb coefficient}``."""
    return {"mu": number_json(mu)}


def profile_identity(profile, path: str | os.PathLike[str] | None = None) -> dict:
    """Which profile the results come from: its file (``path`` as given and the SHA-256 of its
    bytes, when it was read from one), the camera it was made with, how it was fitted, and the
    gripper's geometry (``base_separation`` mm, per finger ``length`` mm, ``theta_entire`` rad,
    ``n_links``)."""
    digest = None
    if path is not None:
        from softgrip_base import input_guard

        try:  # through the input guard: the file may have been swapped for a FIFO or device since
            digest = hashlib.sha256(input_guard.read_user_file(
                path, what="the profile", max_bytes=input_guard.MAX_PROFILE_BYTES, error=OSError)).hexdigest()
        except OSError:
            digest = None
    fingers = {side: {"length": number_json(f.length, 4), "theta_entire": number_json(f.theta_entire, 6),
                      "n_links": int(f.n_links)} for side, f in profile.fingers.items()}
    return {
        "path": None if path is None else str(path),
        "sha256": digest,
        "camera": (profile.camera or {}).get("name"),
        "fit_method": profile.fit.method,
        "estimate_method": profile.fit.estimate_method,
        "base_separation": number_json(profile.base_separation, 4),
        "fingers": fingers,
    }


def document_header(kind: str, profile_id: dict, conventions: dict) -> dict:
    """The fields every document starts with: ``format``, ``kind``, ``units``, ``conventions`` and
    ``profile``."""
    return {"format": f"softgrip-{kind}/{DOCUMENT_VERSIONS.get(kind, 1)}", "kind": kind, "units": conventions["units"],
            "conventions": conventions, "profile": profile_id}


class DocumentWriter:
    """Writes one JSON object whose last field is a list, an element at a time (memory stays that of
    one element): ``header`` first, then each :meth:`add`, then :meth:`close` ends the list and the
    object and adds a newline.

    Example:
        >>> import io
        >>> out = io.StringIO()
        >>> writer = DocumentWriter(out.write, {"kind": "estimate"}, "frames")
        >>> out.getvalue()  # nothing until the first element
        ''
        >>> writer.add({"frame": "a"}); writer.add({"frame": "b"}); writer.close()
        >>> json.loads(out.getvalue())
        {'kind': 'estimate', 'frames': [{'frame': 'a'}, {'frame': 'b'}]}
    """

    def __init__(self, write, header: dict, list_key: str):
        self._write = write
        self._count = 0
        text = json.dumps(header, allow_nan=False)
        # Written with the first element (or at close): a run that fails before any writes nothing.
        self._head: str | None = (text[:-1] + ", " if len(header) else "{") + json.dumps(list_key) + ": ["

    def _start(self) -> str:
        head, self._head = self._head or "", None
        return head

    def add(self, item: dict) -> None:
        self.add_text(json.dumps(item, allow_nan=False))

    def add_text(self, text: str) -> None:
        """Add an element already encoded as JSON text."""
        self._write(self._start() + (", " if self._count else "") + text)
        self._count += 1

    def close(self, trailer: dict | None = None) -> None:
        """End the list; ``trailer``'s fields (if any) follow it in the object."""
        tail = "".join(f", {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in (trailer or {}).items())
        self._write(self._start() + "]" + tail + "}\n")
