"""Parameter sweeps over objects x starts x nK x alpha, locally (joblib) or on Ray."""
