"""Messages and image header stamps from an MCAP bag's indexes: the same messages and
stamps, in the same order, as reading every chunk; None (read the chunks) wherever the
indexes cannot give them."""

import numpy as np
import pytest

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import BagError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.mcap_index import header_stamps, storage_files
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.writer import BagWriter

LEFT, RIGHT, ODOM = "/left/image_raw", "/right/image_raw", "/odom"


def write_bag(path, storage="mcap", rng=None):
    """Images whose header stamps differ from their bag stamps (and go back once on the
    right camera: the stage names that, so the order must be the reader's), big enough to
    span chunks, between odometry messages."""
    rng = rng or np.random.default_rng(0)
    image = rng.integers(0, 255, (120, 160, 3), np.uint8)
    expected = {LEFT: [], RIGHT: []}
    with BagWriter(path, storage) as bag:
        for k in range(40):
            bag_ns = 1_000_000_000 + k * 50_000_000
            for topic, offset in ((LEFT, 7), (RIGHT, 3 if k != 20 else -90_000_000)):
                header_ns = bag_ns - 1_000_000 + offset
                if k % 10 == 0:
                    bag.write(topic.replace("image_raw", "camera_info"), m.CAMERA_INFO, bag_ns,
                              m.camera_info_msg(PinholeCamera(160, 120, fx=100, fy=100, cx=80,
                                                              cy=60), header_ns, "cam"))
                bag.write(topic, m.IMAGE, bag_ns, m.image_msg(image, header_ns, "cam"))
                expected[topic].append(header_ns)
            bag.write(ODOM, m.ODOMETRY, bag_ns + 1,
                      m.odometry_msg(bag_ns, "odom", "base_link", Rigid3.identity(),
                                     np.zeros(3), np.zeros(3)))
    return expected


def read_stamps(path, topics):
    with BagReader(path) as bag:
        out = {t: [] for t in topics}
        for message in bag.messages(topics):
            out[message.topic].append(bag.header_stamp_ns(message))
        return out


def test_indexed_stamps_are_the_messages_stamps_in_order(tmp_path):
    expected = write_bag(tmp_path / "bag")
    assert read_stamps(tmp_path / "bag", [LEFT, RIGHT]) == expected
    with BagReader(tmp_path / "bag") as bag:
        assert bag.indexed_header_stamps([LEFT, RIGHT]) == expected
        assert bag.indexed_header_stamps([LEFT]) == {LEFT: expected[LEFT]}
        assert bag.indexed_header_stamps(["/absent"]) == {"/absent": []}
    files = storage_files(tmp_path / "bag")
    assert files == [tmp_path / "bag" / "bag.mcap"]
    assert header_stamps(files, [LEFT, RIGHT]) == expected  # a bare .mcap file, too
    assert storage_files(files[0]) == files


def all_messages(path, topics, from_index):
    with BagReader(path) as bag:
        return list(bag.messages(topics, from_index=from_index))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_messages_from_the_indexes_are_the_chunks_messages(tmp_path, storage, monkeypatch):
    write_bag(tmp_path / "bag", storage)
    topics = [ODOM, LEFT.replace("image_raw", "camera_info"), RIGHT]
    read = all_messages(tmp_path / "bag", topics, False)
    assert [m.topic for m in read].count(ODOM) == 40 and len(read) == 40 + 4 + 40
    located = []
    import cusfm_ros.io.bags.mcap_index as index

    real = index.indexed_messages
    monkeypatch.setattr(index, "indexed_messages",
                        lambda *a: located.append(found := real(*a)) or found)
    assert all_messages(tmp_path / "bag", topics, True) == read  # topic, type, stamp, bytes
    assert len(located) == (storage == "mcap") and (storage != "mcap" or located[0])


def test_a_message_cut_off_by_a_short_file_is_named(tmp_path):
    write_bag(tmp_path / "bag")
    mcap = tmp_path / "bag" / "bag.mcap"
    with BagReader(tmp_path / "bag") as bag:
        located, _ = bag._located({LEFT})
        mcap.write_bytes(mcap.read_bytes()[:located[5].payload_at + 10])  # after indexing
        with pytest.raises(BagError, match="corrupt or truncated after 5 messages"):
            list(bag._read_located(located, {LEFT: m.IMAGE}))


def test_no_indexed_stamps_where_the_indexes_cannot_give_them(tmp_path):
    write_bag(tmp_path / "bag")
    data = (tmp_path / "bag" / "bag.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:len(data) // 2])  # truncated: no summary
    assert header_stamps([tmp_path / "cut.mcap"], [LEFT]) is None
    write_bag(tmp_path / "db", storage="sqlite3")
    with BagReader(tmp_path / "db") as bag:
        assert bag.indexed_header_stamps([LEFT]) is None
    assert storage_files(tmp_path / "db") is None

    # written with the mcap library, as other recorders do: compressed chunks, chunks
    # without message indexes, no statistics: None; uncompressed and indexed: the stamps
    from mcap.writer import CompressionType, IndexType

    assert header_stamps([write_mcap(tmp_path / "zstd.mcap", CompressionType.ZSTD)],
                         [LEFT]) is None
    assert header_stamps([write_mcap(tmp_path / "chunks.mcap", index_types=IndexType.CHUNK)],
                         [LEFT]) is None
    assert header_stamps([write_mcap(tmp_path / "nostats.mcap", use_statistics=False)],
                         [LEFT]) is None
    assert header_stamps([write_mcap(tmp_path / "plain.mcap")], [LEFT]) == \
        {LEFT: [0, 10, 20, 30, 40]}


def write_mcap(path, compression=None, **options):
    """Five 8x8 images on LEFT, header stamps 0, 10, ... 40 ns, through the mcap library."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as handle:
        writer = Writer(handle, compression=compression or CompressionType.NONE, **options)
        writer.start("ros2", "test")
        schema = writer.register_schema("sensor_msgs/msg/Image", "ros2msg", b"")
        channel = writer.register_channel(LEFT, "cdr", schema)
        for k in range(5):
            raw = m.typestore().serialize_cdr(
                m.image_msg(np.zeros((8, 8, 3), np.uint8), 10 * k, "cam"), m.IMAGE)
            writer.add_message(channel, log_time=k, data=bytes(raw), publish_time=k)
        writer.finish()
    return path


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_keyframes_stage_same_with_or_without_the_indexes(tmp_path, storage, monkeypatch):
    """The stage's first pass takes the stamps from the indexes where it can; the named
    error for stamps that go back is the same either way."""
    from cusfm_ros.errors import BagError
    from cusfm_ros.pipeline.stages.keyframes import KeyframeExtractor

    write_bag(tmp_path / "bag", storage)
    calls = []
    real = BagReader.indexed_header_stamps

    def spy(self, topics):
        calls.append(result := real(self, topics))
        return result

    monkeypatch.setattr(BagReader, "indexed_header_stamps", spy)
    with pytest.raises(BagError, match=r"/right/image_raw: header stamps are not increasing "
                                       r"at image 20"):
        KeyframeExtractor().solve(tmp_path / "bag", tmp_path / "out")
    assert len(calls) == 1 and (calls[0] is None) == (storage == "sqlite3")
