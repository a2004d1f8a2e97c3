"""Parquet columns read row group by row group (crossline.io.columns) against pandas."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from crossline.io.columns import read_columns


def test_read_columns_matches_pandas_over_row_groups(tmp_path):
    rng = np.random.default_rng(4)
    n = 10_007
    labels = np.array(["A", "B", "C", None], dtype=object)[rng.integers(0, 4, n)]
    df = pd.DataFrame({"frame": rng.integers(0, 500, n).astype(np.int64),
                       "laser": labels, "z_cam": rng.normal(120.0, 5.0, n),
                       "width": rng.random(n).astype(np.float32)})
    path = tmp_path / "p.parquet"
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path, row_group_size=1000)
    assert pq.ParquetFile(path).num_row_groups == 11
    got = read_columns(path, ["frame", "laser", "z_cam", "width", "not_there"])
    assert set(got) == {"frame", "laser", "z_cam", "width"}  # a column it lacks is left out
    back = pd.read_parquet(path)
    np.testing.assert_array_equal(got["frame"], back["frame"].to_numpy())
    np.testing.assert_array_equal(got["z_cam"], back["z_cam"].to_numpy())
    assert got["width"].dtype == np.float32
    np.testing.assert_array_equal(got["width"], back["width"].to_numpy())
    # A -> 1, B -> 2, another laser's or a missing label -> 0
    lab = back["laser"]
    expect = np.where(lab == "A", 1, np.where(lab == "B", 2, 0)).astype(np.uint8)
    assert got["laser"].dtype == np.uint8
    np.testing.assert_array_equal(got["laser"], expect)
    assert (got["laser"] == 0).sum() == int(((labels != "A") & (labels != "B")).sum()) > 0
