"""The engine tests' map: the session's rendered references described by its localizer."""

from __future__ import annotations

import pytest

from services.localization.localizer import Localizer
from services.references.memory import MemoryReferenceStore
from tools.synthetic.scene import SyntheticView, encode_png


@pytest.fixture(scope="module")
def store(localizer: Localizer, reference_views: list[SyntheticView]) -> MemoryReferenceStore:
    memory = MemoryReferenceStore()
    for view in reference_views:
        data = localizer.describe_reference(encode_png(view.image), view.camera)
        memory.add(view.name, view.camera, view.cam_from_world, data)
    return memory
