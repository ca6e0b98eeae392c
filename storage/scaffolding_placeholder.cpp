// SCAFFOLDING: removed once storage/ has real sources.
namespace magcal::storage { int scaffolding_placeholder() { return 0; } }
