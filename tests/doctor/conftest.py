"""Fixtures of the doctor's tests (the fake host: fakehost.py)."""
import pytest

from tests.doctor.fakehost import FakeHost


@pytest.fixture
def fake(tmp_path, monkeypatch) -> FakeHost:
    monkeypatch.delenv("RIG_SHM_ROOT", raising=False)  # the rings' default place, /dev/shm/rig, under the fake root
    return FakeHost(tmp_path)
