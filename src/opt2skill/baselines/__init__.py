"""The paper's baselines (Sec. IV-B): kinematic references made by QP inverse kinematics.

`ik_solver` is the QP differential IK (mink on the MuJoCo model) shared by the IK walk and the
human-motion retargeting (`opt2skill.retarget`); `kinematic_record` turns joint-angle frames into a
trajectory record without dynamics; the `walk_ik` task is `opt2skill.tasks.walk_ik`. docs/baselines.md.
"""
