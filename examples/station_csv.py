"""A station's starting point: log a fog-driver daemon's compensated angle to CSV, one row per sample.

    python examples/station_csv.py [HOST:PORT] --out angles.csv [--rate-hz 10] [--count N]

--rate-hz 0 logs every sample.  The daemon's token, when it has one, comes from FOG_DRIVER_TOKEN.  A lost
connection is made again by the library; the samples missed meanwhile are reported on stderr.  drift_sigma_dph
(the drift estimate's 1-sigma) is empty while there is no estimate, and from a daemon before protocol 1.1.
"""

import argparse
import csv
import sys

from fog_driver.client import Client, ClientError, read_token

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("address", nargs="?", default="127.0.0.1:2948")
parser.add_argument("--out", required=True)
parser.add_argument("--rate-hz", type=float, default=10.0)
parser.add_argument("--count", type=int, default=0, help="stop after this many rows (0: never)")
args = parser.parse_args()

try:
    with Client(args.address, token=read_token()) as client, open(args.out, "w", newline="") as f:
        rows = csv.writer(f)
        rows.writerow(["seq", "t_s", "utc", "angle_arcsec", "rate_dph", "drift_dph", "drift_sigma_dph", "flags"])
        for n, a in enumerate(client.angles(rate_hz=args.rate_hz or None), 1):
            if a.gap_before is not None:
                print(f"reconnected: {a.gap_before.missed} samples missed before seq {a.seq}", file=sys.stderr)
            sigma = "" if a.drift_sigma_dph is None else a.drift_sigma_dph
            rows.writerow([a.seq, a.t_s, a.utc, a.angle_arcsec, a.rate_dph, a.drift_dph, sigma, " ".join(a.flags)])
            f.flush()
            if n == args.count:
                break
except ClientError as exc:
    sys.exit(f"station_csv: {exc}")
except KeyboardInterrupt:
    pass
