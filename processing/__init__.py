"""Pure functions over arrays and camera parameters that turn one MCA capture into accurate-depth layers."""
