"""The Python tooling's tests, one folder per `c4g` subpackage. Packages, so that two folders may hold
test files of the same name; `tests.common` holds what they share besides fixtures."""
