// Stands in for a src/ folder that has no sources yet.
