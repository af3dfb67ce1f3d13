"""Learning depth on the robot, online: a stream of frames with odometry and single-point
range readings (`stream`), a bounded replay buffer (`replay`), the learner that predicts,
is scored before it learns (prequential) and trains beside inference (`learner`)."""
