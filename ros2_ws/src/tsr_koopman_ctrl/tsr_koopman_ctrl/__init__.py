"""Tension control of tethered space robot deployment with a learned Koopman model.

Rooms (one subpackage per concern; all but `nodes` are ROS-free):

    control/     the tension laws (one module each), their settings, the output clamp, the loop
    model/       the model file and the learned lifted system in numpy (the controller's form)
    learning/    data, the deep Koopman model and its training (torch), baselines, the error
    bag/         rosbag2-layout MCAP writer and reader, the TSR loop read back from a bag
    evaluation/  a run's figures, the comparison starts, the minimum-time frontier, plots
    nodes/       the controller and recorder nodes (rclpy glue only)
    tools/       command-line tools: deploy, train, evaluate, mpc_sweep; the process launcher
"""
