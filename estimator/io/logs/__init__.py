"""Reading robot logs: ROS 2 MCAP files, rosbag2 folders and live MCAP byte streams.

    config = load_config("configs/humanoid.toml")     # estimator.config
    log = read_log("run.mcap", config)                 # or a rosbag2 folder, a FIFO, "-"
    log.measurements["imu"].values                     # (N, E, K), t_ns (N,) int64

Layout: `source` walks MCAP records (files, folders, FIFOs, stdin, streams; CRC checks, and
salvage of damaged or cut logs into `LostData`), `decode`
turns decoded ROS messages into numpy records (one function per type), `samples` maps them
onto the config's streams and counts bad ones, `reader` / `stream` assemble the results,
`align` puts multi-rate streams on one grid, `ros2_types` names the message types.
"""

from estimator.io.logs.align import align as align
from estimator.io.logs.align import resample as resample
from estimator.io.logs.align import time_grid as time_grid
from estimator.io.logs.measurements import BadSampleCounts as BadSampleCounts
from estimator.io.logs.measurements import Measurement as Measurement
from estimator.io.logs.measurements import Sample as Sample
from estimator.io.logs.measurements import TopicStats as TopicStats
from estimator.io.logs.measurements import collect as collect
from estimator.io.logs.reader import Log as Log
from estimator.io.logs.reader import missing_required as missing_required
from estimator.io.logs.reader import read_log as read_log
from estimator.io.logs.source import LostData as LostData
from estimator.io.logs.stream import ByteStreamReader as ByteStreamReader
