"""The trajectory optimizer's own controller: DDP feedback gains as an expert policy (issue 6)."""

from opt2skill.expert.feedback import FeedbackExpert, pd_targets, servo_torque

__all__ = ["FeedbackExpert", "pd_targets", "servo_torque"]
