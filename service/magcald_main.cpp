// SCAFFOLDING: replaced by the daemon's composition root.
#include <iostream>
int main() {
  std::cerr << "magcald: not built yet\n";
  return 1;
}
