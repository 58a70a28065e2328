"""MuJoCo rollouts of a planned serve (robot, ball and table as native MuJoCo bodies)."""
