"""The 8-DoF serve robot: its description (TOML -> URDF/MJCF), kinematics and dynamics, collision model, ball-in-cup check."""
