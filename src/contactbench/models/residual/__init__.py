"""The residual model: SysID'd MuJoCo plus a learned, projected velocity correction applied inside the rollout."""
