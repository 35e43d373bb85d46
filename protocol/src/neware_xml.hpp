#pragma once
// XML helpers shared by the BTS protocol (neware_bts.cpp) and the step files (neware_stepfile.cpp): both are
// XML from the tester's world, read with Boost.PropertyTree after the vendor normalisation and written by hand.
// Internal to protocol/src. Errors are neware::ProtocolError, as both parsers document.
#include <string>
#include <string_view>

#include <boost/property_tree/ptree.hpp>

namespace cellbench::protocol::neware::xml {

// What is escaped beyond & < > and ". Protocol frames also escape the apostrophe (as the vendor's frames do);
// step files keep the tab, CR and LF of a name or note as character references, so that they read back
// exactly (an XML parser may turn them into spaces inside an attribute value).
enum class Escape { apostrophe, whitespace };

// Appends text escaped for an attribute value or element text.
void append_escaped(std::string& out, std::string_view text, Escape extra);

// The tree of a document after normalize_vendor_xml (comments dropped). A malformed document throws
// ProtocolError "CONTEXTmalformed XML: what (line N)"; context is "" or ends in ": " (e.g. "step file: ").
boost::property_tree::ptree read_document(std::string_view xml, const std::string& context);

}  // namespace cellbench::protocol::neware::xml
