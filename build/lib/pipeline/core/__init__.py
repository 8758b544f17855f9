"""What every method shares: the stage context and cache, MLflow tracking, errors, memory
measurement and report writing."""
