// Files served by the operations server, embedded into the binary at build time (CMake reads
// them into a generated embedded_assets.cpp), so the page works offline and with no install
// layout: the page service/http/page/index.html and Chart.js (Debian libjs-chart.js, UMD build).
#pragma once

#include <string_view>

namespace magcal::http {

extern const std::string_view kIndexHtml;
extern const std::string_view kChartJs;
extern const std::string_view kChartJsVersion;  // from the file's banner, e.g. "3.9.1"

}  // namespace magcal::http
