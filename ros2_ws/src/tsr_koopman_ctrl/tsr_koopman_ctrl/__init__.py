"""Tension control of tethered space robot deployment with a learned Koopman model.

Rooms (one subpackage per concern; all but `nodes`, `deployment`, `launcher` and `testing` are
ROS-free):

    control/       the tension laws (one module each), their settings, the one control step,
                   the output clamp, the ROS-free closed loop
    model/         the model file and the learned lifted system in numpy (the controller's form)
    bag/           rosbag2-layout MCAP writer and reader, the checks a bag must pass, the TSR
                   loop read back from a bag
    evaluation/    a run's figures, the comparison starts, the minimum-time frontier, plots
    learning/      data, the deep Koopman model and its training (torch), retraining from bags,
                   the baselines, the prediction error
    nodes/         the controller and recorder nodes (rclpy glue only)
    deployment     a closed loop over DDS from Python: three processes, a result read from
                   the bag (`Deployment`)
    launcher       nodes as processes (where `ros2 run` finds them)
    commands/      deploy, train, retrain, bag, config: parse, call the API, print
    testing        pytest fixtures for integration tests against the nodes

The studies (tuning, comparison, frontier, robustness, sweeps) are not part of the installed
package: they are the repository's `lab/`.
"""
