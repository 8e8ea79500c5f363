"""Logs in and results out.

logs/          ROS 2 MCAP and rosbag2 logs read into per-stream measurements (files,
               FIFOs, stdin, byte streams), bad samples counted, damaged chunks salvaged
state_topics   the state topics of a log or an estimate (ground truth, /estimate)
mcap_writer    ROS 2 MCAP writing and the state topic layout, for estimates and the
               simulator's logs alike
rerun          the Rerun recording of an estimate
outputs        an output folder or file written whole or not at all
"""
