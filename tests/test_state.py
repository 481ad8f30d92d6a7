"""State containers: ``set`` is ``dataclasses.replace`` without re-running ``__init__``."""
import dataclasses

import pytest
import torch

from torchdem import state as state_module
from torchdem.state import Bodies, PairContacts, State, WallContacts


@pytest.mark.parametrize("cls", [Bodies, PairContacts, WallContacts, State])
def test_set_equals_dataclasses_replace(cls):
    """Same fields, same values, a new object; the original untouched; unknown names refused.
    Holds only while the containers have no __post_init__ (which set() would skip)."""
    assert not hasattr(cls, "__post_init__")
    names = [f.name for f in dataclasses.fields(cls)]
    original = cls(**{n: torch.full((2,), float(k)) for k, n in enumerate(names)})
    changed = {names[0]: torch.zeros(3), names[-1]: torch.ones(4)}
    a = original.set(**changed)
    b = dataclasses.replace(original, **changed)
    assert type(a) is cls and a is not original
    for n in names:
        assert getattr(a, n) is getattr(b, n)
    assert getattr(original, names[0]).shape == (2,)
    with pytest.raises(TypeError, match="unknown field"):
        original.set(not_a_field=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.__setattr__(names[0], None)


def test_every_container_is_covered():
    containers = {c for c in vars(state_module).values()
                  if isinstance(c, type) and issubclass(c, state_module._Replaceable) and c is not state_module._Replaceable}
    assert containers == {Bodies, PairContacts, WallContacts, State}
