"""The application: drives devices, reads raw files, runs processing, stores results, hosts `mca`."""
