"""Policy bundles shipped with the package (`load_bundle("teacher")`, `load_bundle("student")`)."""
