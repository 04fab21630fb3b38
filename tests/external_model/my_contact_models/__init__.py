"""A contact model that lives outside contactbench (docs/ADDING_A_MODEL.md): the test suite runs it end to end."""
