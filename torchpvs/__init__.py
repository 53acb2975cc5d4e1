from .scene import *
