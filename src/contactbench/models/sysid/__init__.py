"""SysID-MuJoCo (paper §4.2): MuJoCo contact parameters fitted to recordings with nevergrad's NGOpt."""
