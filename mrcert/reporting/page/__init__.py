"""The evidence page's sections, one module each; :mod:`mrcert.reporting.results_page` composes them."""
