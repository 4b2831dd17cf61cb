"""Our dependency-free event writer produces files TensorBoard itself reads."""

import pytest

from training.tensorboard import ScalarWriter, crc32c


def test_crc32c_known_value():
    assert crc32c(b"123456789") == 0xE3069283  # the CRC-32C check value


def test_tensorboard_reads_our_scalars(tmp_path):
    event_accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
    writer = ScalarWriter(tmp_path)
    for step in range(5):
        writer.add_scalars(step, {"loss/total": 1.0 / (step + 1), "lr": 1e-4})
    writer.close()
    acc = event_accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    assert set(acc.Tags()["scalars"]) == {"loss/total", "lr"}
    events = acc.Scalars("loss/total")
    assert [e.step for e in events] == [0, 1, 2, 3, 4]
    assert events[3].value == pytest.approx(0.25)
