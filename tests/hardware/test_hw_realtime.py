"""rotation.hardware.realtime: the GC guard that keeps full collections short while a hand runs."""

from __future__ import annotations

import gc
import weakref

from rotation.hardware.realtime import frozen_heap


class Node:
    def __init__(self) -> None:
        self.other = self


def test_frozen_heap_hides_the_existing_heap_and_still_collects_new_cycles():
    old = Node()  # a cycle made before the block: frozen, so a pass inside the block cannot free it
    old_ref = weakref.ref(old)
    del old
    with frozen_heap() as frozen:
        assert frozen > 1_000 and gc.get_freeze_count() > 0
        assert old_ref() is None  # the block starts with a full collection
        young = Node()
        young_ref = weakref.ref(young)
        del young
        gc.collect()
        assert young_ref() is None  # cycles made inside the block are collected as usual
        kept = Node()
        with frozen_heap():  # nested: the inner block leaves the heap frozen for the outer one
            pass
        assert gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == 0  # given back, also when the block raises
    try:
        with frozen_heap():
            raise KeyError("x")
    except KeyError:
        pass
    assert gc.get_freeze_count() == 0 and kept.other is kept
