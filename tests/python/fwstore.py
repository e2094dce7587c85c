"""The tiles a fwlidar voxel store has committed, read without opening it for writing.

Imported by the store checks beside it. A store laid out a file per tile keeps a record per tile
(`fwlidar_state/tiles/TX_TY`, JSON with `watermark` and `chunks`); a store whose tiles are grouped
into shard files (`[voxels] shard_tiles`) keeps a journal instead (`fwlidar_state/journal`: one
line per batch of shards written, `JSON<TAB>CRC-32C`, the JSON holding `seq`, `shards` and
`tiles` as `[tx, ty, watermark, [height chunks]]`; the latest line naming a tile holds it). The
CRC is checked by fwlidar when it opens the store; here a line counts once it is complete (ends in
a newline), as fwlidar counts it.
"""
import json
import os


def committed_tiles(root):
    """{(tx, ty): {"watermark": w, "chunks": [height chunks]}} of the tiles a reader sees.

    A batch whose shards are still pending (a run killed between the journal line and the renames,
    which fwlidar completes when it next opens the store) is not readable yet: its tiles are left
    out.
    """
    tiles = {}
    records = os.path.join(root, "fwlidar_state", "tiles")
    if os.path.isdir(records):
        for name in sorted(os.listdir(records)):
            if name.endswith(".partial"):
                continue
            with open(os.path.join(records, name)) as f:
                rec = json.load(f)
            if rec.get("pending"):
                continue
            tx, ty = (int(v) for v in name.split("_"))
            tiles[(tx, ty)] = {"watermark": rec.get("watermark"), "chunks": rec.get("chunks", [0])}
    journal = os.path.join(root, "fwlidar_state", "journal")
    if os.path.exists(journal):
        with open(journal, "rb") as f:
            lines = f.read().split(b"\n")
        for line in lines[:-1]:  # the last piece is empty or a torn line, never committed
            body, _crc = line.rsplit(b"\t", 1)
            batch = json.loads(body)
            pending = any(
                os.path.exists(os.path.join(root, f"{s}.pending.{batch['seq']}"))
                for s in batch["shards"]
            )
            for tx, ty, watermark, chunks in batch["tiles"]:
                if pending:
                    tiles.pop((tx, ty), None)
                else:
                    tiles[(tx, ty)] = {"watermark": watermark, "chunks": chunks}
    return tiles


def group_tiles(array, tile_columns):
    """Tiles along each side of the array's shard file: 1 when a shard is one tile."""
    shards = array.shards
    return 1 if shards is None else shards[1] // tile_columns
