"""A full disk leaves no trail of empty files: every retry that the disk still refuses
removes what it started, and every file left in the recording directory replays
(``sinewatch replay DIR/*.mcap``, exit 0). A real tmpfs filled to ENOSPC."""

from __future__ import annotations

from conftest import make_config
from test_fault_isolation import _blocks, _fill, _small_disk

from sinewatch.apps.cli import main
from sinewatch.core.pipeline import Pipeline
from sinewatch.outputs.recorder import McapRecorder
from sinewatch.schemas.codec import BLOCK_BINARY_ENCODING, encode_block_binary
from sinewatch.schemas.config import RecordingSection

CHANNELS = 40


def test_a_full_disk_leaves_no_empty_files_and_the_directory_replays(tmp_path):
    with _small_disk(tmp_path / "disk", 4096) as disk:
        config = make_config(
            tmp_path,
            recording=RecordingSection(directory=disk, chunk_size_bytes=4096, rotate_seconds=None, rotate_bytes=None),
            sink_retry_s=1e-9,  # every input during the outage tries to reopen the recording
        )
        recorder = McapRecorder(config, snapshot=lambda: pipeline.snapshot())
        pipeline = Pipeline(config, [recorder])
        # enough channels that the state a new file starts with is larger than a write buffer
        names = [f"f/{i}" for i in range(CHANNELS)]
        blocks = {name: iter(_blocks(name, 25)) for name in names}
        t = 0

        def send(n: int) -> None:
            nonlocal t
            for _ in range(n):
                for name in names:
                    blk = next(blocks[name])
                    t += 1
                    pipeline.process(f"sinewatch/in/{name}", encode_block_binary(blk), BLOCK_BINARY_ENCODING, t)

        send(5)
        filler = _fill(disk)
        send(15)  # the recorder fails, then each input retries against the full disk
        [mcap] = [s for s in pipeline.sinks if s.name == "mcap"]
        assert not mcap.ok and mcap.failures > 10, (mcap.ok, mcap.failures)
        filler.unlink()
        send(5)
        pipeline.release_held(t + 1)  # the input's end, as the daemon's drain
        recorder.close()
        assert pipeline.counters.estimates == 25 * CHANNELS  # estimation never needed the disk
        files = sorted(disk.glob("*.mcap"))
        sizes = {f.name: f.stat().st_size for f in files}
        assert len(files) == 2 and min(sizes.values()) > 0, sizes
        assert main(["replay", *map(str, files), "--no-progress"]) == 0
