// Carries the precompiled header shared by every torch target.
