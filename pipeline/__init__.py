"""frepvdb: FRep and mesh fields to sparse OpenVDB grids."""
