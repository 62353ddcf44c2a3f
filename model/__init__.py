"""The pure math several layers share: transforms, the robot model, the ECS, fringe patterns and
the planner's cell geometry. Depends only on numpy, scipy and ``protocols``."""
