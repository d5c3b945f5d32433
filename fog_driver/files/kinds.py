"""The kinds of file the project writes, by the mark each carries (a leaf: imports nothing).

``outputs.describe`` names an existing file by these marks before refusing to overwrite it; the modules
that write each kind take its mark from here.
"""

#: A capture's provenance sidecar (``CAPTURE.bin.yaml``): its ``format`` tag.
PROVENANCE_FORMAT = "fog_driver capture provenance"
#: The provenance sidecar ``compensate`` writes beside its CSV (``OUT.csv.yaml``): its ``format`` tag.
COMPENSATE_PROVENANCE_FORMAT = "fog_driver compensate provenance"
#: A fitted drift model file: its ``format`` tag.
MODEL_FORMAT = "fog_driver drift model"
#: An adaptation state file (``--adapt-state``): its ``format`` tag.
ADAPT_STATE_FORMAT = "fog_driver adaptation state"
#: The simulator's truth file: its first line.
TRUTH_HEADER = "# fog_driver simulator truth: one row per device second; see fog_driver/sim/capture.py"
#: The columns of a ``compensate`` CSV, in order (its header line is them joined by commas).
#: ``drift_sigma_dph`` is the last: it came after the others, and a reader by position keeps working.
ROW_COLUMNS = (
    "t_s",
    "n_samples",
    "rate_raw_dph",
    "drift_dph",
    "rate_comp_dph",
    "angle_raw_arcsec",
    "angle_comp_arcsec",
    "t_top_c",
    "t_bottom_c",
    "t_housing_c",
    "flags",
    "drift_sigma_dph",
)
#: The columns every ``compensate`` CSV starts with, those written before ``drift_sigma_dph`` included:
#: ``outputs.describe`` recognises one by them.
ROW_COLUMNS_FIRST = ROW_COLUMNS[: ROW_COLUMNS.index("flags") + 1]
