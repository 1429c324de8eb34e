import sys
h = "{'descr': '" + 'x' * 60000 + "', 'fortran_order': False, 'shape': (1,), }"
h = h + ' ' * (63 - (len(h) + 10) % 64) + '\n'
open(sys.argv[1], 'wb').write(b'\x93NUMPY\x01\x00' + len(h).to_bytes(2, 'little') + h.encode())
print('ok')
