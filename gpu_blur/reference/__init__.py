"""The numpy float64 reference of every stage: the truth every kernel backend is checked against."""
