"""Term names usable in a config's ``[model].terms`` list: the base library and the
diagnosis catalogue's effects (:mod:`fricjax.model.effects`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from fricjax.model.drive import HarmonicDrive, MeasuredInput
from fricjax.model.effects import EFFECTS
from fricjax.model.friction import CoulombViscous, StribeckFriction
from fricjax.model.term import Term

TermFactory = Callable[..., Term]

TERMS: dict[str, TermFactory] = {
    HarmonicDrive.name: HarmonicDrive,
    MeasuredInput.name: MeasuredInput,
    StribeckFriction.name: StribeckFriction,
    CoulombViscous.name: CoulombViscous,
    **{cls.name: cls for cls in EFFECTS},
}


def make_term(name: str, options: Mapping[str, Any]) -> Term:
    return TERMS[name](**options)
